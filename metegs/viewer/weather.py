"""The viewer's weather: slider values -> θ (with the run's camera spec) -> weather models for any viewing camera,
and the run's met record as a timeline of hours."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from datetime import datetime, timedelta

import numpy as np
import torch

from metegs.cameras import Cameras
from metegs.meteo import Theta, intensity_class, theta_from_values
from metegs.registry import registry
from metegs.weather.base import WeatherModel, WeatherModelConfig, WeatherScene, model_seed
from metegs.weather.compose import build_weather_models
from metegs.weather.conditions import ConditionsConfig, theta_camera

DEFAULT_WEATHER = ("rain-streaks", "fog-analytic")
"""Weather models of the viewer for runs that model none (plain 3DGS)."""
CLEAR_VISIBILITY_M = 20_000.0
"""Visibility at the top of the slider: clear air, no fog."""
STORM_SWEEP_MM_H = (0.5, 100.0)
"""Precipitation of the first and last frame of the default weather sweep (light -> violent rain)."""


@dataclass(frozen=True)
class WeatherValues:
    """What the weather sliders say."""

    precip_mm_h: float = 0.0
    """Rain rate, mm/h (0: no rain)."""
    visibility_m: float | None = None
    """Visibility, m (None: clear air)."""
    wind_speed_m_s: float = 0.0
    """Wind speed, m/s."""
    wind_dir_deg: float | None = None
    """Direction the wind blows from, degrees clockwise from north (None: unknown)."""
    exposure_s: float = 1.0 / 60.0
    """Exposure time of the camera, s."""

    def describe(self, exposure: bool = True) -> str:
        """One line: rate with its WMO class, visibility, wind (and the exposure)."""
        p = self.precip_mm_h
        rate = "no rain" if p <= 0 else f"{p:.3g} mm/h ({intensity_class(p)}, WMO)"
        vis = "clear" if self.visibility_m is None else f"{self.visibility_m:,.0f} m"
        wind = f"{self.wind_speed_m_s:.1f} m/s" + (
            "" if self.wind_dir_deg is None else f" from {self.wind_dir_deg:.0f}°"
        )
        text = f"{rate} · visibility {vis} · wind {wind}"
        return text + (f" · exposure {format_exposure(self.exposure_s)}" if exposure else "")


def format_exposure(seconds: float) -> str:
    """1/60 s style for short exposures, else seconds."""
    if seconds < 0.5:
        return f"1/{round(1.0 / seconds):d} s"
    return f"{seconds:.2g} s"


def values_from_theta(theta: Theta, exposure_s: float) -> WeatherValues:
    """The slider values that reproduce θ's conditions."""
    c = theta.conditions
    return WeatherValues(
        precip_mm_h=float(c.precip_mm_per_h or 0.0) if theta.rain.active else 0.0,
        visibility_m=c.visibility_m if c.visibility_m is not None and c.visibility_m < CLEAR_VISIBILITY_M else None,
        wind_speed_m_s=float(c.wind_speed_m_per_s or 0.0),
        wind_dir_deg=c.wind_dir_deg_from,
        exposure_s=exposure_s,
    )


class ViewerWeather:
    """The run's weather models rebuilt for the viewer: θ from slider values, models per viewing camera.

    θ is mapped with the run's camera spec (`theta_camera` of the training cameras), so streak sizes and counts mean
    what they meant in training; the models are rebuilt (through `build_weather_models`, plugins included) for each
    viewing camera, from one reference image that stands for all training views (drop colour, airlight), with north
    pinned to the training views' mean direction so that the wind blows the same way whichever way the viewer looks.
    Every registered weather model can be switched on (`set_models`), with the run's config where it has one.
    """

    def __init__(
        self,
        names: Sequence[str],
        cameras: Cameras,
        images: list[torch.Tensor] | None,
        up: np.ndarray,
        metres_per_unit: float,
        conditions: ConditionsConfig,
        seed: int = 0,
        config_of: Callable[[str], WeatherModelConfig] | None = None,
    ):
        self.cameras = cameras
        self.metres_per_unit = float(metres_per_unit)
        self.capture_width_px = conditions.capture_width_px
        self.up = torch.as_tensor(np.asarray(up), dtype=torch.float32)
        self.seed = seed
        self.north = cameras.camera_to_worlds[:, :3, 2].double().mean(0)
        """[3] the training views' mean viewing direction: north of every viewing camera's weather."""
        self.config_of = config_of or (lambda name: registry("weather").get(name)())
        """A weather model's config by registry name (the run's own where it has one)."""
        self.names: list[str] = []
        """Registry names of the weather models shown."""
        self.configs: list[WeatherModelConfig] = []
        """Their configs."""
        self.set_models(names)
        self.reference = reference_image(images) if images else None
        self.theta: Theta | None = None
        self.values: WeatherValues | None = None

    def set_models(self, names: list[str]) -> None:
        """Show the registered weather models ``names`` (the run's configs where it has them)."""
        current = dict(zip(self.names, self.configs))
        self.configs = [current[n] if n in current else self.config_of(n) for n in names]
        self.names = list(names)

    def set_values(self, values: WeatherValues) -> Theta:
        """Map the values to θ (the run's camera spec with the slider's exposure) and keep it."""
        spec = theta_camera(self.cameras, self.metres_per_unit, values.exposure_s, self.capture_width_px)
        self.theta = theta_from_values(
            values.precip_mm_h, values.visibility_m, values.wind_speed_m_s, values.wind_dir_deg, camera=spec
        )
        self.values = values
        return self.theta

    def models_for(self, camera: Cameras) -> list[WeatherModel]:
        """Weather models of the current θ for one viewing camera (its view index is 0)."""
        if self.theta is None:
            raise RuntimeError("set_values() first")
        scene = WeatherScene(
            cameras=camera,
            up=self.up.to(camera.device),
            metres_per_unit=self.metres_per_unit,
            images=None if self.reference is None else [self.reference.to(camera.device)],
            seed=self.seed,
            north=self.north,
        )
        return [m.to(camera.device) for m in build_weather_models(self.configs, self.theta, scene)]


def reference_image(images: list[torch.Tensor], max_views: int = 16) -> torch.Tensor:
    """Up to ``max_views`` views, evenly picked and stacked into one image [sum H, W, 3] (resized to the first's width)."""
    import torch.nn.functional as F

    pick = np.unique(np.linspace(0, len(images) - 1, min(len(images), max_views)).round().astype(int))
    width = int(images[pick[0]].shape[1])
    rows = []
    for i in pick:
        im = images[i].detach().float().cpu()
        if im.shape[1] != width:
            h = max(1, round(im.shape[0] * width / im.shape[1]))
            im = F.interpolate(im.permute(2, 0, 1)[None], size=(h, width), mode="area")[0].permute(1, 2, 0)
        rows.append(im)
    return torch.cat(rows, dim=0).clamp(0, 1)


@dataclass(frozen=True)
class RecordHour:
    """The weather of one hour of a met record."""

    time: datetime
    """Time (UTC)."""
    values: WeatherValues
    """Slider values of that hour (visibility None when the record has none)."""
    label: str
    """One line for the GUI."""


class MetTimeline:
    """Hours of a met record (the run's, else the shipped storm), each with its aggregated weather."""

    def __init__(self, conditions: ConditionsConfig):
        from metegs.meteo import DEFAULT_CAPTURE_TIME, parse_time
        from metegs.meteo.theta_plan import load_record

        self.source = "shipped storm (Beijing, 11 Aug 2013)" if conditions.record is None else str(conditions.record)
        self.table, _ = load_record(conditions.record)
        self.window, self.agg = conditions.window, conditions.agg
        start, end = self.table.start_utc, self.table.end_utc
        hours = max(0, int((end - start).total_seconds() // 3600))
        first = start.replace(minute=0, second=0, microsecond=0)
        self.times = [first + timedelta(hours=h) for h in range(hours + 1)]
        if conditions.time is not None:
            capture = parse_time(conditions.time)
        elif conditions.record is None:
            capture = DEFAULT_CAPTURE_TIME
        else:
            capture = self.times[0]
        self.capture_index = int(np.argmin([abs((t - capture).total_seconds()) for t in self.times]))
        self._cache: dict[int, RecordHour] = {}

    def __len__(self) -> int:
        return len(self.times)

    def hour(self, index: int, exposure_s: float) -> RecordHour:
        """The weather of hour ``index`` (aggregated over the run's window, as in training)."""
        from metegs.meteo import conditions_at

        index = min(max(int(index), 0), len(self.times) - 1)
        if index not in self._cache:
            t = self.times[index]
            near = self.table.between(t - timedelta(hours=6), t + timedelta(hours=6))
            c = conditions_at(near if len(near) else self.table, t, self.window, self.agg)
            values = WeatherValues(
                precip_mm_h=float(c.precip_mm_per_h or 0.0) if c.rain_active else 0.0,
                visibility_m=c.visibility_m if c.visibility_m is not None and not c.visibility_at_least else None,
                wind_speed_m_s=float(c.wind_speed_m_per_s or 0.0),
                wind_dir_deg=c.wind_dir_deg_from,
            )
            label = f"{t:%Y-%m-%d %H:%M}Z: {values.describe(exposure=False)}"
            if c.visibility_m is None:
                label = label.replace("visibility clear", "no visibility in the record")
            self._cache[index] = RecordHour(t, values, label)
        hour = self._cache[index]
        return dataclasses.replace(hour, values=dataclasses.replace(hour.values, exposure_s=exposure_s))

    def at(self, position: float, exposure_s: float) -> tuple[datetime, WeatherValues]:
        """Time and weather at ``position`` hours after the record's first hour (a fraction blends two hours)."""
        position = min(max(float(position), 0.0), len(self.times) - 1.0)
        i = min(int(math.floor(position)), len(self.times) - 1)
        s = position - i
        a = self.hour(i, exposure_s).values
        b = self.hour(min(i + 1, len(self.times) - 1), exposure_s).values
        return self.times[i] + timedelta(hours=s), blend_values(a, b, s)


def blend_values(a: WeatherValues, b: WeatherValues, s: float) -> WeatherValues:
    """Weather a fraction ``s`` of the way from ``a`` to ``b``: rain rate and wind speed linear, visibility linear in
    its logarithm (clear air counts as `CLEAR_VISIBILITY_M`), wind direction and exposure those of the nearer."""
    near = a if s < 0.5 else b
    va, vb = (CLEAR_VISIBILITY_M if v.visibility_m is None else v.visibility_m for v in (a, b))
    visibility = math.exp((1 - s) * math.log(va) + s * math.log(vb))
    return dataclasses.replace(
        near,
        precip_mm_h=(1 - s) * a.precip_mm_h + s * b.precip_mm_h,
        visibility_m=None if visibility >= CLEAR_VISIBILITY_M * (1 - 1e-9) else visibility,
        wind_speed_m_s=(1 - s) * a.wind_speed_m_s + s * b.wind_speed_m_s,
    )


@dataclass
class RunWeather:
    """A trained run's weather, ready to render from any camera."""

    weather: ViewerWeather
    """The run's weather models (set to ``values``)."""
    values: WeatherValues
    """The weather the run trained under (its θ as slider values)."""
    timeline: MetTimeline | None
    """Hours of the run's met record (the shipped storm's when the record cannot be read; None when neither can)."""
    note: str
    """Why the values or timeline are not the run's own ("" when they are)."""


def run_weather(trainer) -> RunWeather:
    """The weather of ``trainer``'s run: its weather models (or `DEFAULT_WEATHER` for a run without any, such as
    plain 3DGS), its θ as values and its met record as hours."""
    from metegs.engine.metegs_config import MeteGSConfig, plugin_weather_fields
    from metegs.errors import MetegsError
    from metegs.weather.conditions import DEFAULT_EXPOSURE_S, scene_metres_per_unit, theta_for_cameras

    c, ds = trainer.config, trainer.dataset
    names = list(getattr(c, "weather", ()) or DEFAULT_WEATHER)
    own = c.weather_config if isinstance(c, MeteGSConfig) else plugin_weather_fields(MeteGSConfig)().weather_config
    mpu = scene_metres_per_unit(c.conditions, trainer.scene.metric_scale)
    train = ds.cameras[ds.train_indices]
    images = [ds.images[i] for i in ds.train_indices]
    weather = ViewerWeather(names, train, images, trainer.scene.up, mpu, c.conditions, model_seed(c.seed), own)
    exposure = c.conditions.exposure_s
    if exposure is None:
        exposure = float(train.exposure_time_s[0]) if train.exposure_time_s is not None else DEFAULT_EXPOSURE_S
    note = ""
    try:
        theta = trainer.theta
        if theta is None:
            theta = theta_for_cameras(c.conditions, trainer.scene.cameras, mpu)
        values = values_from_theta(theta, exposure)
    except (MetegsError, OSError) as exc:
        values = WeatherValues(precip_mm_h=6.8, exposure_s=exposure)
        note = f"the run's weather could not be mapped ({exc}); starting from 6.8 mm/h"
    timeline = None
    try:
        timeline = MetTimeline(c.conditions)
    except (MetegsError, OSError) as exc:
        note = f"the run's met record is unavailable ({exc}); the timeline shows the shipped storm"
        try:
            timeline = MetTimeline(ConditionsConfig())
        except (MetegsError, OSError):
            timeline = None
    weather.set_values(values)
    return RunWeather(weather, values, timeline, note)


def sweep_rates(frames: int, low_mm_h: float, high_mm_h: float) -> list[float]:
    """Rain rates of a weather sweep: ``frames`` rates, log-spaced from ``low_mm_h`` to ``high_mm_h``."""
    if frames < 2:
        return [high_mm_h]
    lo, hi = math.log(max(low_mm_h, 1e-3)), math.log(max(high_mm_h, 1e-3))
    return [math.exp(lo + (hi - lo) * i / (frames - 1)) for i in range(frames)]
