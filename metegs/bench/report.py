"""The suite's report: ordering checks, markdown tables in the paper's layout, PSNR-vs-time plots.

``results.md`` holds, per scene, the comparison table (rows: methods; columns: conditions x PSNR↑ /
SSIM↑ / LPIPS↓; the best value of a column in **bold**, the second <u>underlined</u>; rows marked
*oracle*, which see clean photos or clean references, are not ranked), one detail table per condition (PSNR / SSIM / LPIPS,
training time, Gaussian count, render frames/s), the ablation table, the rows repeated with other seeds (mean ±
standard deviation), the conditions (record, time, θ) and the checks. ``plots/<scene>__<condition>.png`` draws
every method's test PSNR against its wall time (training, plus the restoration time for restored photos; the
clean-photo rows dashed).
"""

from __future__ import annotations

import math
import statistics
from pathlib import Path
from typing import Any

from metegs.bench.plot import Series, write_line_chart
from metegs.files import atomic_write_text

HIGHER_IS_BETTER = {"psnr": True, "ssim": True, "lpips": False, "time_seconds": False, "render_fps": True}
FORMATS = {"psnr": "{:.2f}", "ssim": "{:.4f}", "lpips": "{:.4f}", "time_seconds": "{:.1f}", "render_fps": "{:.1f}"}


def _value(record: dict | None, metric: str) -> float | None:
    if record is None or record.get("status") == "failed" or record.get("status") == "skipped":
        return None
    v = record.get(metric)
    return float(v) if isinstance(v, (int, float)) and math.isfinite(v) else None


def cell_records(runs: list[dict], scene: str, condition: str | None) -> dict[str, dict]:
    """method -> record of one (scene, condition) cell; clean-photo runs (condition None) count in every cell."""
    out = {}
    for r in runs:
        if r["scene"] == scene and (r["condition"] == condition or r["condition"] is None):
            out[r["method"]] = r
    return out


def evaluate_checks(suite, runs: list[dict], conditions: dict) -> list[dict]:
    """One entry per (check, metric, scene, condition, pair): passed True / False, or None when a value is missing."""
    out = []
    for check in suite.checks:
        for scene in [s.name for s in suite.scenes]:
            if check.scenes and scene not in check.scenes:
                continue
            for name, cond in conditions.items():
                if check.conditions and name not in check.conditions:
                    continue
                if check.kinds and cond.kind not in check.kinds:
                    continue
                cell = cell_records(runs, scene, name)
                if not any(r["condition"] == name for r in cell.values()):
                    continue  # this cell was not run
                for metric in check.metrics:
                    for a, op, b in check.chain():
                        va, vb = _value(cell.get(a), metric), _value(cell.get(b), metric)
                        passed = None
                        if va is not None and vb is not None:
                            sa, sb = (va, vb) if HIGHER_IS_BETTER[metric] else (-va, -vb)
                            passed = sa > sb + check.margin if op == ">" else sa >= sb - check.tolerance
                        out.append(
                            {
                                "expect": check.expect,
                                "pair": f"{a} {op} {b}"
                                + (f" + {check.margin:g}" if op == ">" and check.margin else ""),
                                "metric": metric,
                                "scene": scene,
                                "condition": name,
                                "left": va,
                                "right": vb,
                                "passed": passed,
                            }
                        )
    return out


def _rank_marks(values: dict[str, float | None], higher: bool) -> dict[str, str]:
    """method -> 'best' / 'second' among the distinct values present."""
    present = sorted({v for v in values.values() if v is not None}, reverse=higher)
    marks: dict[str, str] = {}
    if len(present) < 2:  # nothing to tell apart
        return marks
    for name, v in values.items():
        if v is None:
            continue
        if present and v == present[0]:
            marks[name] = "best"
        elif len(present) > 1 and v == present[1]:
            marks[name] = "second"
    return marks


def _fmt(v: float | None, metric: str, mark: str | None = None) -> str:
    if v is None:
        return "–"
    s = FORMATS.get(metric, "{:g}").format(v)
    return f"**{s}**" if mark == "best" else f"<u>{s}</u>" if mark == "second" else s


def _label(method: dict) -> str:
    return f"*{method['label']} (oracle)*" if method.get("oracle") else method["label"]


def _table(header: list[str], rows: list[list[str]], align: list[str] | None = None) -> str:
    align = align or ["l"] + ["r"] * (len(header) - 1)
    sep = ["---:" if a == "r" else "---" for a in align]
    lines = ["| " + " | ".join(header) + " |", "| " + " | ".join(sep) + " |"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


def comparison_table(results: dict, scene: str, group: str = "main") -> str | None:
    """Rows: the group's methods; columns: each condition's PSNR / SSIM / LPIPS (paper layout)."""
    methods = [m for m in results["methods"] if m["group"] == group]
    conds = [
        c for c in results["conditions"] if any(r["scene"] == scene and r["condition"] == c for r in results["runs"])
    ]
    if not methods or not conds:
        return None
    metrics = ("psnr", "ssim", "lpips")
    header = ["Method"] + [f"{c} {m.upper()}{'↑' if HIGHER_IS_BETTER[m] else '↓'}" for c in conds for m in metrics]
    cells = {c: cell_records(results["runs"], scene, c) for c in conds}
    marks = {}
    for c in conds:
        for m in metrics:
            ranked = {x["name"]: _value(cells[c].get(x["name"]), m) for x in methods if not x.get("oracle")}
            marks[(c, m)] = _rank_marks(ranked, HIGHER_IS_BETTER[m])
    rows = []
    for x in methods:
        row = [_label(x)]
        for c in conds:
            for m in metrics:
                row.append(_fmt(_value(cells[c].get(x["name"]), m), m, marks[(c, m)].get(x["name"])))
        rows.append(row)
    return _table(header, rows)


def detail_table(results: dict, scene: str, condition: str | None) -> str | None:
    """Every method of one cell: PSNR, SSIM, LPIPS, time, Gaussians, render frames/s."""
    cell = cell_records(results["runs"], scene, condition)
    methods = [m for m in results["methods"] if m["name"] in cell]
    if not methods:
        return None
    cols = ("psnr", "ssim", "lpips", "time_seconds", "render_fps")
    marks = {
        c: _rank_marks(
            {m["name"]: _value(cell[m["name"]], c) for m in methods if not m.get("oracle")}, HIGHER_IS_BETTER[c]
        )
        for c in cols
    }
    rows = []
    for m in methods:
        r = cell[m["name"]]
        if r.get("status") in ("failed", "skipped"):
            why = (r.get("error") or "").splitlines()[0][:90]
            rows.append([_label(m), f"{r['status']}: {why}", "", "", "", "", ""])
            continue
        rows.append(
            [_label(m)]
            + [_fmt(_value(r, c), c, marks[c].get(m["name"])) for c in cols[:4]]
            + [
                str(r.get("num_gaussians", "–")),
                _fmt(_value(r, "render_fps"), "render_fps", marks["render_fps"].get(m["name"])),
            ]
        )
    header = ["Method", "PSNR↑", "SSIM↑", "LPIPS↓", "Time (s)↓", "Gaussians", "Render FPS↑"]
    return _table(header, rows)


def ablation_table(results: dict, scene: str) -> str | None:
    """Ablation rows (and methods with an ``ablation_label``): PSNR / SSIM per condition they ran on."""
    rows_m = [
        m
        for m in results["methods"]
        if (m["group"] == "ablation" or m.get("ablation_label")) and not m.get("seed_of")  # copies: `seeds_table`
    ]
    if not rows_m:
        return None
    conds = [
        c
        for c in results["conditions"]
        if any(r["scene"] == scene and r["condition"] == c and r["group"] == "ablation" for r in results["runs"])
    ]
    if not conds:
        return None
    header = ["Row"] + [f"{c} {m}" for c in conds for m in ("PSNR↑", "SSIM↑")] + ["mean PSNR↑", "mean SSIM↑"]
    cells = {c: cell_records(results["runs"], scene, c) for c in conds}
    values = {}
    for m in rows_m:
        vals = {(c, k): _value(cells[c].get(m["name"]), k) for c in conds for k in ("psnr", "ssim")}
        for k in ("psnr", "ssim"):
            got = [vals[(c, k)] for c in conds if vals[(c, k)] is not None]
            vals[("mean", k)] = sum(got) / len(got) if len(got) == len(conds) else None
        values[m["name"]] = vals
    keys = [(c, k) for c in conds for k in ("psnr", "ssim")] + [("mean", "psnr"), ("mean", "ssim")]
    marks = {key: _rank_marks({n: v[key] for n, v in values.items()}, True) for key in keys}
    rows = [
        [m.get("ablation_label") or m["label"]]
        + [_fmt(values[m["name"]][key], key[1], marks[key].get(m["name"])) for key in keys]
        for m in sorted(rows_m, key=lambda m: m.get("ablation_label") or m["label"])
    ]
    return _table(header, rows)


def seeds_table(results: dict, scene: str) -> str | None:
    """The rows trained again with other seeds (``seeds``): per condition, PSNR and SSIM as mean ± standard deviation
    over the row and its copies that finished, with their number."""
    copies: dict[str, list[str]] = {}
    for m in results["methods"]:
        if m.get("seed_of"):
            copies.setdefault(m["seed_of"], []).append(m["name"])
    bases = [m for m in results["methods"] if m["name"] in copies]
    conds = [
        c
        for c in (*results["conditions"], None)
        if any(r["scene"] == scene and r["condition"] == c and r["method"] in copies for r in results["runs"])
    ]
    if not bases or not conds:
        return None
    seeds = {m["name"]: m.get("seed") for m in results["methods"]}

    def spread(values: list[float], fmt: str) -> str:
        if len(values) < 2:
            return f"{fmt.format(values[0])} (1)" if values else "–"
        return f"{fmt.format(statistics.mean(values))} ± {fmt.format(statistics.stdev(values))} ({len(values)})"

    header = ["Row (seeds)"] + [f"{c or 'clean photos'} {m}" for c in conds for m in ("PSNR↑", "SSIM↑")]
    rows = []
    for m in bases:
        names = [m["name"], *copies[m["name"]]]
        row = [f"{_label(m)} ({', '.join(str(seeds[n]) for n in names)})"]
        for c in conds:
            here = cell_records(results["runs"], scene, c)
            for k in ("psnr", "ssim"):
                got = [v for n in names if (v := _value(here.get(n), k)) is not None]
                row.append(spread(got, FORMATS[k]))
        rows.append(row)
    return _table(header, rows)


def conditions_table(results: dict) -> str:
    rows = []
    for name, c in results["conditions"].items():
        rain, fog = c.get("rain") or {}, c.get("fog") or {}
        src = []
        if rain:
            src.append(f"{Path(rain['record']).name} {rain['time']}" if "record" in rain else "explicit rain")
        if fog:
            src.append(f"{Path(fog['record']).name} {fog['time']}" if "record" in fog else "explicit visibility")
        theta = next(iter((c.get("theta") or {}).values()), {}) if c.get("theta") else {}
        beta = theta.get("fog_beta_per_m")
        rows.append(
            [
                name,
                c["kind"],
                c.get("family", "physical"),
                "; ".join(src),
                "–" if not rain else f"{rain.get('precip_mm_h')} ({rain.get('wmo_class', '')})",
                "–"
                if not fog
                else f"{fog.get('visibility_m'):g}"
                + (f" ({', '.join(fog.get('present_weather') or [])})" if fog.get("present_weather") else ""),
                "–" if not theta else str(theta.get("streaks_per_view")),
                "–" if beta is None else f"{beta:.2e}",
            ]
        )
    header = [
        "Condition",
        "Kind",
        "Weather made by",
        "Record and time (UTC)",
        "Rain mm/h (WMO)",
        "Visibility m",
        "θ streaks/view",
        "θ fog β /m",
    ]
    return _table(header, rows, ["l", "l", "l", "l", "r", "r", "r", "r"])


def checks_table(results: dict) -> str | None:
    checks = results.get("checks") or []
    if not checks:
        return None
    rows = []
    for c in checks:
        status = {True: "pass", False: "**FAIL**", None: "n/a"}[c["passed"]]
        lv = "–" if c["left"] is None else f"{c['left']:.4g}"
        rv = "–" if c["right"] is None else f"{c['right']:.4g}"
        rows.append([c["pair"], c["metric"], c["scene"], c["condition"], f"{lv} vs {rv}", status])
    return _table(
        ["Expectation", "Metric", "Scene", "Condition", "Values", "Result"], rows, ["l", "l", "l", "l", "r", "l"]
    )


def curve_series(results: dict, scene: str, condition: str) -> list[Series]:
    cell = cell_records(results["runs"], scene, condition)
    series = []
    for m in results["methods"]:
        r = cell.get(m["name"])
        if r is None or r.get("status") in ("failed", "skipped"):
            continue
        hist = r.get("history") or []
        xs = [h["time_seconds"] for h in hist]
        ys = [h["psnr"] for h in hist]
        series.append(Series(m["label"], xs, ys, dashed=bool(m.get("oracle"))))
    return series


def _runs_wall(results: dict) -> str:
    """', the runs took N s of wall time in all' (over every invocation that trained them), with what is unknown."""
    total, unknown = results.get("runs_wall_seconds"), results.get("runs_wall_unknown") or 0
    if not total:
        return ""
    known = f"; its runs took {total:.0f} s of wall time in all (over the invocations that trained them"
    return known + (f"; {unknown} earlier runs not timed)" if unknown else ")")


def markdown_report(results: dict, plots: dict[tuple[str, str], Path] | None = None) -> str:
    out = [f"# Benchmark `{results['suite']}`", ""]
    if results.get("description"):
        out += [results["description"], ""]
    host = results.get("host", {})
    out += [
        f"{results['created']}; {results['total_seconds']:.0f} s for this invocation{_runs_wall(results)}; "
        f"torch {host.get('torch')}, "
        f"{host.get('threads')} threads, {host.get('cuda') or 'CPU'}. PSNR / SSIM / LPIPS on the clean held-out "
        "views; time = training seconds (+ restoration seconds for restored photos); render FPS of the final "
        "model over the test views. Best in **bold**, second <u>underlined</u>; *oracle* rows (which see clean photos or clean references) "
        "are not ranked.",
        "",
        "## Conditions",
        "",
        conditions_table(results),
        "",
    ]
    for scene in results["scenes"]:
        out += [f"## {scene}", ""]
        table = comparison_table(results, scene)
        if table:
            out += [table, ""]
        for cond in results["conditions"]:
            table = detail_table(results, scene, cond)
            if not table or not any(r["scene"] == scene and r["condition"] == cond for r in results["runs"]):
                continue
            out += [f"### {scene} / {cond}", "", table, ""]
            if plots and (scene, cond) in plots:
                out += [f"![PSNR against time]({plots[(scene, cond)].as_posix()})", ""]
        if not any(r["scene"] == scene and r["condition"] is not None for r in results["runs"]):
            table = detail_table(results, scene, None)  # clean-photo runs only (a peer-parity suite, say)
            if table:
                out += [f"### {scene} / clean photos", "", table, ""]
        table = ablation_table(results, scene)
        if table:
            out += [f"### {scene}: ablations", "", table, ""]
        table = seeds_table(results, scene)
        if table:
            out += [f"### {scene}: across seeds", "", "Mean ± standard deviation (finished runs).", "", table, ""]
    table = checks_table(results)
    if table:
        verdict = "all hold" if results.get("all_checks_passed") else "**some fail**"
        out += ["## Checks", "", f"Expected orderings: {verdict}.", "", table, ""]
    failed = [r for r in results["runs"] + results.get("support_runs", []) if r.get("status") in ("failed", "skipped")]
    if failed:
        out += ["## Runs that did not finish", ""]
        out += [
            f"- {r['scene']} / {r['condition'] or 'clean'} / {r['method']}: {r['status']}: "
            f"{(r.get('error') or '').splitlines()[0]}"
            for r in failed
        ]
        out.append("")
    return "\n".join(out)


def write_report(results: dict, output: Path) -> dict[str, Any]:
    """results.md and plots/*.png in ``output``; -> {"markdown": path, "plots": [paths]}."""
    output = Path(output)
    plots = {}
    for scene in results["scenes"]:
        for cond in results["conditions"]:
            if not any(r["scene"] == scene and r["condition"] == cond for r in results["runs"]):
                continue
            series = curve_series(results, scene, cond)
            rel = Path("plots") / f"{scene}__{cond}.png"
            write_line_chart(output / rel, series, f"{results['suite']}: {scene} / {cond} - test PSNR against time")
            plots[(scene, cond)] = rel
    md = output / "results.md"
    atomic_write_text(md, markdown_report(results, plots))
    return {"markdown": md, "plots": [output / p for p in plots.values()]}
