"""`metegs-meteo`: look at a station record and the weather parameters θ it maps to.

    metegs-meteo summary FILE [--reader NAME] [--start T] [--end T] [--set KEY=VALUE ...]
    metegs-meteo at FILE --time T [--window 1h] [--agg max] [--exposure-s 0.004]

Without FILE both use the storm excerpt shipped with metegs (Beijing, 11 August 2013).
"""

from __future__ import annotations

import json
import sys
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import tyro
from rich.console import Console
from rich.table import Table

from metegs.cli import run_cli
from metegs.errors import ConfigError
from metegs.meteo import (
    DEFAULT_CAPTURE_TIME,
    CameraSpec,
    ObservationTable,
    Theta,
    conditions_at,
    default_storm_path,
    default_storm_record,
    intensity_class,
    map_conditions,
    parse_options,
    parse_time,
    precip_series,
    read_observations,
)
from metegs.meteo.observations import epoch_s, from_epoch_s


def load_table(file: Path | None, reader: str | None, options: tuple[str, ...]) -> ObservationTable:
    """The record in ``file`` (or the shipped storm when None)."""
    if file is None:
        if reader is not None or options:
            raise ConfigError("--reader/--set need a FILE")
        return default_storm_record()
    return read_observations(file, reader, **parse_options(options))


@dataclass
class Summary:
    """Print a table of the record's period (rate, WMO class, visibility, wind) and write a PNG plot."""

    file: tyro.conf.Positional[Path | None] = None
    """Station record or forecast file; none: the storm excerpt shipped with metegs."""
    reader: str | None = None
    """Reader name (csv, metar, ghcnh, isd, open-meteo, or a plugin's); none: detected from the file."""
    set: tuple[str, ...] = ()
    """Reader options as KEY=VALUE (e.g. year=2024 month=7 for METAR, precip_column=RAIN for csv)."""
    start: str | None = None
    """First time to show (ISO 8601, UTC unless an offset is given)."""
    end: str | None = None
    """Last time to show."""
    station: str | None = None
    """Station to show, for files holding several."""
    plot: Path | None = None
    """PNG to write; default: <file stem>-meteo.png in the current folder."""
    max_rows: int = 40
    """At most this many table rows; longer periods are shown in equal time bins."""
    exposure_s: float = 1.0 / 60.0
    """Exposure time for the mapped N_rain in the plot, s."""

    def run(self, console: Console) -> Path:
        from metegs.files import atomic_write_bytes
        from metegs.meteo.plot import render_summary_png

        table = load_table(self.file, self.reader, self.set)
        stations = table.stations
        station = self.station if self.station is not None else (stations[0] if len(stations) > 1 else None)
        if self.station is None and len(stations) > 1:
            console.print(f"[yellow]{len(stations)} stations in the file; showing {station} (choose with --station)[/]")
        table = table.for_station(station)
        start = parse_time(self.start) if self.start else table.start_utc
        end = parse_time(self.end) if self.end else table.end_utc
        shown = table.between(start, end)
        if not len(shown):
            raise ConfigError(f"no records between {start} and {end}")
        series = precip_series(table)
        s0, s1 = epoch_s(start), epoch_s(end)
        first_start = float(series.start_s.min()) if len(series) else s0
        s0 = min(s0, max(first_start, s0 - 24 * 3600)) if self.start is None else s0
        rate_at_end = {round(e): r for e, r in zip(series.end_s, series.rate_mm_per_h)}
        rows = [(r, rate_at_end.get(round(epoch_s(r.time_utc)))) for r in shown]
        self._print(console, table, shown, series, rows, s0, s1)
        png = render_summary_png(
            table,
            series,
            start_s=s0,
            end_s=s1,
            camera=CameraSpec(exposure_s=self.exposure_s),
            title=f"{Path(table.source).name}  {shown.records[0].station}",
        )
        out = self.plot or Path(f"{Path(table.source).stem}-meteo.png")
        atomic_write_bytes(out, png)
        console.print(f"wrote {out}", soft_wrap=True, highlight=False)
        return out

    def _print(self, console: Console, table, shown, series, rows, s0: float, s1: float) -> None:
        sel = (series.end_s > s0) & (series.start_s < s1)
        hours = np.clip(np.minimum(series.end_s[sel], s1) - np.maximum(series.start_s[sel], s0), 0, None) / 3600.0
        total_mm = float(np.sum(series.rate_mm_per_h[sel] * hours))
        classes = Counter()
        for r, h in zip(series.rate_mm_per_h[sel], hours):
            classes[intensity_class(float(r))] += h
        covered = float(hours.sum())
        span_h = (s1 - s0) / 3600.0
        console.print(
            f"[bold]{Path(table.source).name}[/] ({table.reader}) station {shown.records[0].station or '-'}: "
            f"{len(shown)} records {shown.start_utc:%Y-%m-%d %H:%M}Z .. {shown.end_utc:%Y-%m-%d %H:%M}Z; "
            f"precipitation {total_mm:.1f} mm over {covered:.1f} h of data ({span_h - covered:.1f} h without), "
            f"max {float(series.rate_mm_per_h[sel].max()) if sel.any() else 0:.1f} mm/h; hours by WMO class: "
            + ", ".join(f"{k} {v:.1f}" for k, v in sorted(classes.items(), key=lambda kv: -kv[1])),
            highlight=False,
        )
        for note in table.notes:
            console.print(f"[dim]note: {note}[/]")
        grid = Table(show_lines=False, padding=(0, 1), collapse_padding=True)
        for col in ("time (UTC)", "rate mm/h", "class", "visibility m", "wind m/s", "from °", "weather"):
            grid.add_column(
                col,
                justify="right" if col not in ("time (UTC)", "class", "weather") else "left",
                no_wrap=col != "weather",
                min_width=8 if col == "weather" else None,
            )
        if len(rows) <= self.max_rows:
            for r, rate in rows:
                grid.add_row(
                    f"{r.time_utc:%Y-%m-%d %H:%M}",
                    "-" if rate is None else f"{rate:.2f}",
                    "-" if rate is None else intensity_class(rate),
                    _vis(r.visibility_m, r.visibility_at_least, r.visibility_below),
                    "-" if r.wind_speed_m_per_s is None else f"{r.wind_speed_m_per_s:.1f}",
                    "-" if r.wind_dir_deg_from is None else f"{r.wind_dir_deg_from:.0f}",
                    "-" if r.weather is None else " ".join(w.code for w in r.weather) or "none",
                )
        else:
            edges = np.linspace(epoch_s(rows[0][0].time_utc), epoch_s(rows[-1][0].time_utc) + 1, self.max_rows + 1)
            grid.columns[0].header = "bin start (UTC)"
            grid.columns[1].header = "max rate mm/h"
            grid.columns[4].header = "mean wind m/s"
            times = np.array([epoch_s(r.time_utc) for r, _ in rows])
            for a, b in zip(edges, edges[1:]):
                chunk = [rows[i] for i in np.nonzero((times >= a) & (times < b))[0]]
                if not chunk:
                    continue
                rates = [rt for _, rt in chunk if rt is not None]
                vis = [
                    (r.visibility_m, r.visibility_at_least, r.visibility_below)
                    for r, _ in chunk
                    if r.visibility_m is not None
                ]
                winds = [r.wind_speed_m_per_s for r, _ in chunk if r.wind_speed_m_per_s is not None]
                wx = sorted({w.code for r, _ in chunk for w in (r.weather or ())})
                grid.add_row(
                    f"{from_epoch_s(a):%Y-%m-%d %H:%M}",
                    f"{max(rates):.2f}" if rates else "-",
                    intensity_class(max(rates)) if rates else "-",
                    _vis(*min(vis)) if vis else "-",
                    f"{np.mean(winds):.1f}" if winds else "-",
                    "",
                    " ".join(wx) or "-",
                )
        console.print(grid)


def _vis(v: float | None, at_least: bool = False, below: bool = False) -> str:
    if v is None:
        return "-"
    return (">=" if at_least else "<" if below else "") + f"{v:.0f}"


@dataclass
class At:
    """Print θ (θ_rain, θ_fog, θ_drops) for one capture time."""

    file: tyro.conf.Positional[Path | None] = None
    """Station record or forecast file; none: the storm excerpt shipped with metegs."""
    time: str | None = None
    """Capture time (ISO 8601, UTC unless an offset is given); none with no FILE: the storm's default time."""
    window: str = "1h"
    """Aggregation window around the time (e.g. 30min, 1h, 3h)."""
    agg: Literal["mean", "max", "min"] = "max"
    """Aggregation of the window."""
    align: Literal["center", "before", "after"] = "center"
    """Where the window lies relative to the time."""
    reader: str | None = None
    """Reader name; none: detected from the file."""
    set: tuple[str, ...] = ()
    """Reader options as KEY=VALUE."""
    station: str | None = None
    """Station, for files holding several."""
    exposure_s: float = 1.0 / 60.0
    """Camera exposure time, s."""
    focal_px: float = 1000.0
    """Camera focal length, pixels."""
    json: bool = False
    """Print θ as JSON instead of tables."""

    def run(self, console: Console) -> Theta:
        time = self.time
        if time is None:
            if self.file is not None:
                raise ConfigError("--time is needed with a FILE (e.g. --time 2013-08-11T07:40Z)")
            time = DEFAULT_CAPTURE_TIME
        table = load_table(self.file, self.reader, self.set)
        conditions = conditions_at(table, time, self.window, self.agg, align=self.align, station=self.station)
        theta = map_conditions(conditions, CameraSpec(exposure_s=self.exposure_s, focal_px=self.focal_px))
        if self.json:
            Console(highlight=False, soft_wrap=True).print_json(json.dumps(theta.to_dict()))
            return theta
        source = Path(table.source).name if self.file is not None else f"{default_storm_path().name} (shipped storm)"
        console.print(
            f"[bold]θ[/] for {conditions.time_utc:%Y-%m-%d %H:%M}Z from {source}, {self.window} window ({self.align}), agg {self.agg}"
        )
        for title, obj in (
            ("conditions", conditions),
            ("θ_rain", theta.rain),
            ("θ_fog", theta.fog),
            ("θ_drops", theta.drops),
        ):
            grid = Table(title=title, show_header=False, title_justify="left")
            grid.add_column("name")
            grid.add_column("value", justify="right")
            for key, value in theta.to_dict()[_key(title)].items() if title != "conditions" else _conditions_items(obj):
                grid.add_row(key, _fmt(value))
            console.print(grid)
        for note in conditions.notes:
            console.print(f"[dim]note: {note}[/]")
        return theta


def _key(title: str) -> str:
    return {"θ_rain": "rain", "θ_fog": "fog", "θ_drops": "drops"}[title]


def _conditions_items(c) -> list[tuple[str, Any]]:
    return [
        ("precip_mm_per_h", c.precip_mm_per_h),
        ("precip_source", c.precip_source),
        ("precip_coverage", c.precip_coverage),
        ("precip_kind", c.precip_kind),
        ("intensity_class", c.intensity_class),
        ("wmo_score", c.wmo_score),
        ("normalised s_t", c.normalised),
        ("visibility_m", c.visibility_m),
        ("visibility_at_least", c.visibility_at_least),
        ("wind_speed_m_per_s", c.wind_speed_m_per_s),
        ("wind_dir_deg_from", c.wind_dir_deg_from),
        ("weather", " ".join(w.code for w in c.weather) or ("none" if c.weather_reported else "not reported")),
        ("rain_active", c.rain_active),
        ("fog_active", c.fog_active),
        ("station", c.station),
    ]


def _fmt(value: Any) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, (list, tuple)):
        return "(" + ", ".join(_fmt(v) for v in value) + ")"
    return str(value)


def main(argv: list[str] | None = None) -> Any:
    console = Console()
    command = tyro.extras.subcommand_cli_from_dict(
        {"summary": Summary, "at": At},
        prog="metegs-meteo",
        description="Read a station record or forecast, grade it and map it to weather parameters θ.",
        args=sys.argv[1:] if argv is None else argv,
    )
    return command.run(console)


def entrypoint() -> None:
    run_cli(main)


if __name__ == "__main__":
    entrypoint()
