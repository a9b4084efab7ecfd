"""CPU time the hypervisor gave to other machines while a benchmark ran (Linux "steal" time)."""

from __future__ import annotations

from pathlib import Path

PROC_STAT = Path("/proc/stat")


def cpu_times(stat: Path = PROC_STAT) -> tuple[int, int] | None:
    """(steal, total) clock ticks of all CPUs since boot from the "cpu" line of /proc/stat; None where unavailable."""
    try:
        fields = stat.read_text().splitlines()[0].split()
    except (OSError, IndexError):
        return None
    if len(fields) < 9 or fields[0] != "cpu":
        return None
    ticks = [int(v) for v in fields[1:]]
    # user nice system idle iowait irq softirq steal [guest guest_nice]: guest time is already in user/nice
    return ticks[7], sum(ticks[:8])


class StealMeter:
    """Fraction of the machine's CPU time stolen by the hypervisor between `start` and `fraction`."""

    def __init__(self, stat: Path = PROC_STAT):
        self.stat = stat
        self.start_times = cpu_times(stat)

    def fraction(self) -> float | None:
        """Stolen / all CPU time since the meter started (None without /proc/stat or with no time elapsed)."""
        end = cpu_times(self.stat)
        if self.start_times is None or end is None or end[1] <= self.start_times[1]:
            return None
        return (end[0] - self.start_times[0]) / (end[1] - self.start_times[1])
