"""Steal time of the benchmark host, from /proc/stat."""

from metegs.bench.steal import StealMeter, cpu_times


def _stat(path, user, idle, steal):
    # cpu user nice system idle iowait irq softirq steal guest guest_nice
    path.write_text(f"cpu  {user} 0 10 {idle} 0 0 0 {steal} 5 0\ncpu0 1 2 3 4 5 6 7 8 9 10\n")


def test_steal_fraction_is_the_stolen_share_of_the_elapsed_ticks(tmp_path):
    stat = tmp_path / "stat"
    _stat(stat, user=100, idle=50, steal=40)
    assert cpu_times(stat) == (40, 200)  # guest ticks are not counted twice
    meter = StealMeter(stat)
    assert meter.fraction() is None  # no time elapsed
    _stat(stat, user=160, idle=70, steal=60)  # 100 more ticks, 20 of them stolen
    assert meter.fraction() == 0.2


def test_missing_or_malformed_stat_gives_no_figure(tmp_path):
    assert cpu_times(tmp_path / "absent") is None
    bad = tmp_path / "bad"
    bad.write_text("intr 1 2 3\n")
    assert cpu_times(bad) is None
    assert StealMeter(tmp_path / "absent").fraction() is None
