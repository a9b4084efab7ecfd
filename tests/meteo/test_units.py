"""Unit conversions: exact factors, aliases, and clear errors for units that do not exist."""

from __future__ import annotations

import math

import pytest

from metegs.errors import ConfigError
from metegs.meteo import units


def test_exact_factors():
    assert units.to_mm(0.25, "in") == pytest.approx(6.35)  # METAR P0025 (§6.1)
    assert units.to_mm(1.2, "cm") == pytest.approx(12.0)
    assert units.to_m(0.25, "SM") == pytest.approx(402.336)  # 1/4SM
    assert units.to_m(16.093, "km") == pytest.approx(16093.0)
    assert units.to_m_per_s(12, "kt") == pytest.approx(6.1733, abs=1e-4)
    assert units.to_m_per_s(36, "km/h") == pytest.approx(10.0)
    assert units.to_m_per_s(10, "mph") == pytest.approx(4.4704)


def test_aliases_and_case():
    assert units.to_mm(1, "Inches") == pytest.approx(25.4)
    assert units.to_m_per_s(1, "KT") == units.to_m_per_s(1, "knots")


@pytest.mark.parametrize("unit", ["furlong", "mm/h/h", "", "kelvin"])
def test_unknown_unit_is_a_clear_error(unit):
    with pytest.raises(units.UnitError, match="unknown length unit"):
        units.to_mm(1.0, unit)
    assert issubclass(units.UnitError, ConfigError)


def test_speed_unit_is_not_a_length():
    with pytest.raises(units.UnitError, match="known: "):
        units.to_m(1.0, "kt")


@pytest.mark.parametrize(
    ("text", "seconds"), [("1h", 3600), ("30min", 1800), ("1h30min", 5400), ("90", 90), ("2d", 172800), (45, 45)]
)
def test_durations(text, seconds):
    assert units.parse_duration_s(text) == seconds


@pytest.mark.parametrize("text", ["soon", "1 fortnight", "-1h", "h"])
def test_bad_durations(text):
    with pytest.raises(ConfigError):
        units.parse_duration_s(text)


def test_compass_points():
    assert units.compass_to_deg("N") == 0
    assert units.compass_to_deg("nne") == 22.5
    assert units.compass_to_deg("WNW") == 292.5
    assert math.isnan(units.compass_to_deg("C"))
    with pytest.raises(ConfigError, match="unknown compass direction"):
        units.compass_to_deg("NORTHISH")
    assert units.wind_to_deg(270) == 90
