"""The MeteGS dual-branch method end to end on a tiny degraded synthetic scene."""

import json
from dataclasses import replace

import numpy as np
import pytest
import torch

from metegs.data.config import DatasetConfig, SyntheticSceneConfig
from metegs.densify.adc import ADCConfig
from metegs.engine.metegs_config import MeteGSConfig
from metegs.engine.metegs_trainer import (
    DENSE_OPTICAL_DEPTH,
    MIN_AIRLIGHT_OUTSHINES,
    MIN_MEDIUM_EXPLAINED,
)
from metegs.losses.photometric import PhotometricLossConfig
from metegs.models.gtn import GTNConfig
from metegs.render import RenderSettings
from metegs.weather.conditions import ConditionsConfig
from metegs.weather.fog_analytic import FogAnalytic, FogAnalyticConfig
from metegs.weather.learnable import LearnableTransients


def tiny_metegs(tmp_path, **kw) -> MeteGSConfig:
    ds = DatasetConfig(synthetic=SyntheticSceneConfig(width=64, height=48, num_views=12, num_points=600))
    options = dict(
        method="metegs-full",
        max_steps=40,
        output_dir=tmp_path,
        experiment_name="run",
        device="cpu",
        progress=False,
        dataset=ds,
        checkpoint_every=20,
        eval_every=0.5,
        densify=ADCConfig(max_gaussians=1500),
        conditions=ConditionsConfig(precip_mm_h=20.0, visibility_m=400.0, wind_speed_m_s=4.0, wind_dir_deg=90.0),
        compare_baseline=False,
        robust=record_robust(),
    )
    options.update(kw)
    return MeteGSConfig(**options)


def record_robust(**kw):
    """The robust mask as the record's rain alone decides it: the tiny scene's faint streaks would keep it off."""
    from metegs.losses.robust import RobustMaskConfig

    return RobustMaskConfig(min_stroke_energy=0.0, **kw)


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("metegs")
    trainer = tiny_metegs(tmp).setup()
    metrics = trainer.train()
    return trainer, metrics


def test_run_writes_clean_scene_side_by_sides_and_decisions(trained):
    trainer, metrics = trained
    run = trainer.run_dir
    for name in ("config.yml", "metrics.json", "scene.ply", "decisions.json", "checkpoints/step-000040.ckpt"):
        assert (run / name).is_file(), name
    compare = sorted((run / "renders" / "test").glob("*_compare.png"))
    assert len(compare) == len(trainer.dataset.test_indices) > 0
    saved = json.loads((run / "metrics.json").read_text())
    assert saved["reference"] == "clean" and saved["method"] == "metegs-full"
    decisions = json.loads((run / "decisions.json").read_text())
    assert {"degrade", "weather rain-streaks", "weather fog-analytic", "gtn", "clean branch"} <= set(
        decisions["decisions"]
    )
    assert decisions["theta"]["rain"]["precip_mm_per_h"] == 20.0


def test_degraded_photos_train_and_references_stay_clean(trained):
    trainer, _ = trained
    ds = trainer.dataset
    i = ds.train_indices[0]
    assert ds.clean_images is not None
    diff = (ds.images[i] - ds.clean_images[i]).abs().mean()
    assert diff > 0.01  # the photos carry the weather, the references do not


def test_weather_gaussians_never_reach_the_scene_model(trained):
    trainer, _ = trained
    rain = next(m for m in trainer.weather_models if isinstance(m, LearnableTransients))
    n_rain = len(rain.gaussians_for(trainer.dataset.train_indices[0]))
    assert n_rain > 0
    from metegs.gaussians.ply import load_ply

    ply = load_ply(trainer.run_dir / "scene.ply")
    assert len(ply) == len(trainer.model)
    streak_means = rain.views[str(trainer.dataset.train_indices[0])].means
    d = torch.cdist(streak_means[:50], ply.params["means"].detach()).amin(1)
    assert bool((d > 0).all())


def test_fog_parameters_learned_from_their_theta_start(trained):
    trainer, metrics = trained
    fog = next(m for m in trainer.weather_models if m.name == "fog-analytic")
    beta0 = torch.tensor(trainer.theta.fog.beta_rgb_per_m)
    assert not torch.allclose(fog.beta_rgb.detach().cpu(), beta0.float(), rtol=1e-4)
    saved = json.loads((trainer.run_dir / "metrics.json").read_text())["weather"]["fog-analytic"]
    assert saved["beta_per_m"] == pytest.approx(fog.beta_rgb.tolist(), rel=1e-4)
    from metegs.weather.medium import fog_extinction_rgb

    start = fog_extinction_rgb(trainer.theta, include_rain_veil=True)  # θ's fog and the rain's veil
    assert saved["record_beta_per_m"] == pytest.approx(start.tolist(), rel=1e-4)


def forward_facing(scene):
    """``scene`` with every view turned like the first, side by side along its x axis (a forward-facing rig)."""
    c2w = scene.cameras.camera_to_worlds.clone()
    c2w[:, :3, :3] = c2w[0, :3, :3]
    c2w[:, :3, 3] = c2w[0, :3, 3] + torch.linspace(-0.5, 0.5, len(c2w))[:, None] * c2w[0, :3, 0]
    return replace(scene, cameras=replace(scene.cameras, camera_to_worlds=c2w))


def test_fog_record_prior_is_on_where_the_views_see_the_scene_from_one_distance(tmp_path):
    """The built-in scene's views surround it (points seen from distances twice apart): the photos measure β. A
    forward-facing rig (all views side by side, looking the same way) cannot: β is held near the record's."""
    conditions = ConditionsConfig(precip_mm_h=0.0, visibility_m=300.0, metres_per_unit=100.0)
    around = tiny_metegs(tmp_path / "around", conditions=conditions, max_steps=1).setup()
    assert around.decisions["fog-analytic prior"].startswith("off: the views see a scene point from distances")
    fog = next(m for m in around.weather_models if m.name == "fog-analytic")
    assert not fog.use_record_prior and fog.prior(0) is None
    assert around.decisions["fog-analytic layers"].startswith("on:")  # and how it thins with height
    assert fog.height_rate.requires_grad
    learned = {id(p) for o in around.method_optimizers.values() for g in o.param_groups for p in g["params"]}
    assert id(fog.height_rate) in learned
    facing = tiny_metegs(tmp_path / "facing", conditions=conditions, max_steps=1).setup(
        scene=forward_facing(around.scene)
    )
    assert facing.decisions["fog-analytic prior"].startswith("on (weight 0.1)")
    fog = next(m for m in facing.weather_models if m.name == "fog-analytic")
    assert fog.use_record_prior and float(fog.prior(0).detach()) == 0.0
    assert facing.decisions["fog-analytic layers"].startswith("off:") and not fog.layered


def test_the_airlight_learns_its_directions_only_where_the_views_see_the_scene_along_many(tmp_path):
    """Asked to (opt-in), around the built-in scene in fog the airlight learns how it changes with the viewing
    direction (in the weather optimiser); a forward-facing rig sees each surface along one direction and keeps one
    airlight, as every run does by default."""
    conditions = ConditionsConfig(precip_mm_h=0.0, visibility_m=300.0, metres_per_unit=100.0)
    default = tiny_metegs(tmp_path / "default", conditions=conditions, max_steps=1, clean_supervision=False).setup()
    assert default.decisions["fog-analytic airlight"].startswith("one for every direction (--fog-analytic.airlight")
    assert not next(m for m in default.weather_models if m.name == "fog-analytic").directional
    asked = dict(
        conditions=conditions, max_steps=1, clean_supervision=False, fog_analytic=FogAnalyticConfig(airlight_degree=2)
    )
    around = tiny_metegs(tmp_path / "around", **asked).setup()
    assert around.decisions["fog-analytic airlight"].startswith("changes with the viewing direction: spherical")
    fog = next(m for m in around.weather_models if m.name == "fog-analytic")
    learned = {id(p) for o in around.method_optimizers.values() for g in o.param_groups for p in g["params"]}
    assert fog.directional and id(fog.airlight_sh) in learned
    facing = tiny_metegs(tmp_path / "facing", **asked).setup(scene=forward_facing(around.scene))
    assert facing.decisions["fog-analytic airlight"].startswith("one for every direction: the views see a scene")
    assert not next(m for m in facing.weather_models if m.name == "fog-analytic").directional


def test_blind_the_record_holds_beta_where_heavy_rain_falls_through_dense_fog(tmp_path):
    """The built-in scene's views measure β (the test above), but heavy rain through dense fog adds light that
    differs per view: blind, where the scene's points bear the record's fog out (a uniform medium explains 12 % there;
    in fog too dense to see the scene through they cannot, and the dark channel holds it), β stays near the record's;
    clean references measure it, and it stays free."""
    conditions = ConditionsConfig(precip_mm_h=20.0, visibility_m=300.0, metres_per_unit=100.0)
    blind = tiny_metegs(tmp_path / "blind", conditions=conditions, clean_supervision=False, max_steps=1).setup()
    assert blind.decisions["fog-analytic prior"].startswith("on (weight 0.1): the views see a scene point from")
    assert "heavy rain (20 mm/h) through dense fog" in blind.decisions["fog-analytic prior"]
    fog = next(m for m in blind.weather_models if m.name == "fog-analytic")
    assert fog.use_record_prior and not fog.layered
    assert blind.decisions["fog-analytic layers"].startswith("off: the rain that drowns the photos' measure of β")
    refs = tiny_metegs(tmp_path / "refs", conditions=conditions, max_steps=1).setup()
    assert refs.decisions["fog-analytic prior"].startswith("off: the views see a scene point from")
    light = replace(conditions, precip_mm_h=1.0)
    blind = tiny_metegs(tmp_path / "light", conditions=light, clean_supervision=False, max_steps=1).setup()
    # light rain: the photos measure β, and β is held at their measure, not the record's
    assert "the photos measure β" in blind.decisions["fog-analytic prior"]
    assert "through dense fog" not in blind.decisions["fog-analytic prior"]


@pytest.mark.parametrize("height_rate", [2.0, -2.0])
def test_held_fog_starts_its_layers_where_the_points_read_it_thinning_upwards(tmp_path, monkeypatch, height_rate):
    """Where β is held at the points' measure, the layered fit of the same points sets where β and its height profile
    start if it thins upwards (scale height 50 m); where it reads denser upwards, as uniform fogs read, β stays one at
    every height."""
    from metegs.weather.medium_fit import MediumFit

    fit = MediumFit(beta_per_m=0.02, height_rate=height_rate, airlight=(0.8, 0.8, 0.8), observations=10, points=5)
    monkeypatch.setattr("metegs.engine.metegs_trainer.fit_medium", lambda *args, **kwargs: fit)
    conditions = ConditionsConfig(precip_mm_h=0.0, visibility_m=300.0, metres_per_unit=10.0)
    trainer = tiny_metegs(tmp_path, conditions=conditions, max_steps=1, clean_supervision=False).setup()
    fog = next(m for m in trainer.weather_models if m.name == "fog-analytic")
    layers = trainer.decisions["fog-analytic layers"]
    assert "the photos measure β" in trainer.decisions["fog-analytic prior"]
    assert fog.height_rate.requires_grad == (height_rate > 0)
    if height_rate > 0:
        assert layers.endswith(
            "from the points' measure of how: 2.00e-02/m at the cameras' mean height, scale height 50 m"
        )
        assert float(fog.height_rate.detach()) == height_rate and fog.measured_beta == 0.02
        assert float(fog.prior_log_beta.mean().exp()) == pytest.approx(0.02, rel=1e-5)
    else:
        assert layers.startswith("off: the points read the fog denser upwards (scale height -50 m)")
        assert not fog.layered and fog.measured_beta != 0.02


def test_the_dark_channel_prior_holds_the_fog_where_blind_photos_cannot_measure_it(tmp_path, monkeypatch):
    """Blind on a forward-facing rig the dark-channel prior holds the medium (the record's β is where it starts, not a
    prior) and moves β; where the views measure β (the built-in scene's surround), with clean references, or off, the
    record prior decides as before."""
    from metegs.losses.dark_channel import DarkChannelPriorConfig

    conditions = ConditionsConfig(precip_mm_h=0.0, visibility_m=300.0, metres_per_unit=10.0)  # t ≈ 0.5 far
    around = tiny_metegs(tmp_path / "around", conditions=conditions, max_steps=1, clean_supervision=False).setup()
    assert around.dehazing == [] and around.decisions["dark channel prior"].startswith("off: the views see a scene")
    assert around.decisions["fog-analytic prior"].startswith("on (weight 0.1): the views see a scene point from")
    assert "the photos measure β" in around.decisions["fog-analytic prior"]  # at the scene's points
    # the points read this uniform fog denser upwards, as they read every uniform fog, so it stays uniform
    assert around.decisions["fog-analytic layers"].startswith("off: the points read the fog denser upwards (scale")
    # in fog dense at the scene's depth the points' measure holds it too (the Lund street in metegs's own 200 m fog:
    # 12.71 dB, 10.19 under the dark channel), and where they do not measure it the prior does
    thick = replace(conditions, visibility_m=60.0)
    dense = tiny_metegs(tmp_path / "dense", conditions=thick, max_steps=1, clean_supervision=False).setup()
    assert dense.medium_optical_depth >= DENSE_OPTICAL_DEPTH and dense.dehazing == []
    assert dense.decisions["dark channel prior"].startswith("off: the views see a scene point from distances")
    assert "the photos measure β" in dense.decisions["dark channel prior"]
    fog = next(m for m in dense.weather_models if m.name == "fog-analytic")
    assert fog.use_record_prior and fog.measured_beta is not None
    assert float(fog.log_beta.detach().mean().exp()) == pytest.approx(fog.measured_beta, rel=1e-5)
    assert "the photos measure β" in dense.decisions["fog-analytic prior"]
    monkeypatch.setattr("metegs.engine.metegs_trainer.MIN_MEDIUM_EXPLAINED", 1.01)  # nothing explains that much
    unmeasured = tiny_metegs(tmp_path / "unmeasured", conditions=thick, max_steps=1, clean_supervision=False).setup()
    assert len(unmeasured.dehazing) == 1
    assert unmeasured.decisions["dark channel prior"].startswith("on: the views see a scene point from distances")
    assert (
        "but the medium's optical depth at the scene's typical depth is" in unmeasured.decisions["dark channel prior"]
    )
    # held under the airlight estimated at the start, lowered where the scene's points fit it darker
    held = next(m for m in unmeasured.weather_models if m.name == "fog-analytic")
    words = ", ".join(f"{float(a):.2f}" for a in held.airlight)
    lowered = f"under the airlight ({words}) that the scene's points fit along with β, darker than the photos'"
    estimated = f"under the airlight estimated at the start ({words}), which the scene's points leave as it is"
    assert (lowered in unmeasured.decisions["dark channel prior"]) != (
        estimated in unmeasured.decisions["dark channel prior"]
    )
    assert not held.airlight_logit.requires_grad
    monkeypatch.undo()
    # heavy rain through it keeps the record prior where the points bear that fog out (the Lund street, independent
    # rain + fog: 13.36 dB, 11.22 with the dark channel) ...
    rain = replace(thick, precip_mm_h=20.0)
    rainy = tiny_metegs(tmp_path / "rainy", conditions=rain, max_steps=1, clean_supervision=False).setup()
    assert rainy.dehazing == [] and rainy.decisions["fog-analytic prior"].startswith("on (weight 0.1)")
    assert "which bear the record's fog out" in rainy.decisions["dark channel prior"]
    # ... and the dark channel holds it where they do not (the kitchen's independent rain + fog, whose fog is 3.5x
    # thinner at the cameras than the record's: 14.23 dB, 11.25 under the record's β)
    monkeypatch.setattr("metegs.engine.metegs_trainer.MIN_MEDIUM_EXPLAINED", 1.01)
    unborne = tiny_metegs(tmp_path / "unborne", conditions=rain, max_steps=1, clean_supervision=False).setup()
    assert len(unborne.dehazing) == 1 and unborne.decisions["fog-analytic prior"].startswith("off: the dark channel")
    assert "do not bear the record's fog out" in unborne.decisions["dark channel prior"]
    assert "heavy rain (20 mm/h)" in unborne.decisions["dark channel prior"]
    monkeypatch.undo()
    # random points fill the views' overlap and say nothing of the scene's distances: the prior holds the fog there
    # (the instant-ngp fox under independent rain + fog, 4 points triangulated: 16.71 dB with it, 15.15 without)
    scattered = tiny_metegs(
        tmp_path / "random",
        conditions=conditions,
        max_steps=1,
        clean_supervision=False,
        model=replace(around.config.model, random_init=True),
    ).setup()
    assert len(scattered.dehazing) == 1
    assert scattered.decisions["dark channel prior"].startswith("on: the Gaussians start from random points")
    rig = forward_facing(around.scene)
    blind = tiny_metegs(tmp_path / "blind", conditions=conditions, max_steps=40, clean_supervision=False).setup(
        scene=rig
    )
    assert blind.decisions["dark channel prior"].startswith("on: the views see a scene point")
    assert blind.decisions["fog-analytic prior"].startswith("off: the dark channel prior measures β")
    (fog,) = blind.dehazing
    assert fog.name == "fog-analytic" and not fog.use_record_prior
    start, airlight = fog.log_beta.detach().clone(), fog.airlight.detach().clone()
    # once the surfaces are opaque (the prior looks through rendered surfaces only), β moves by it
    held = [blind.train_step(i).get("dark_channel", 0.0) for i in blind.dataset.train_indices * 3]
    assert max(held) > 0.0 and not torch.equal(fog.log_beta.detach(), start)
    # the airlight stays at its estimate (a free one drifts down while a pale scene takes the haze in)
    assert (
        torch.equal(fog.airlight.detach(), airlight)
        and "airlight estimated at the start" in blind.decisions["dark channel prior"]
    )
    # and it measures the fog patch by patch: a per-view grid scales the optical depth, learned with the rest
    assert blind.decisions["fog-analytic patches"].startswith("on: per view, a 4x")
    assert (
        fog.patch_log_scale.requires_grad
        and fog.patchy
        and not torch.equal(fog.patch_log_scale.detach(), torch.zeros_like(fog.patch_log_scale))
    )
    # but not in the rain's thin veil alone, where the grid takes in the rain's light (the Ethiopian head, blind:
    # metegs's own heavy rain 23.02 dB without it, 22.35 with; the independent 22.13 without, 21.86 with)
    rain_only = ConditionsConfig(precip_mm_h=20.0, metres_per_unit=10.0)
    veiled = tiny_metegs(tmp_path / "veil", conditions=rain_only, max_steps=1, clean_supervision=False).setup(scene=rig)
    (veil,) = veiled.dehazing
    assert veiled.decisions["fog-analytic patches"].startswith("off: the record gives no visibility")
    assert not veil.patch_log_scale.requires_grad and not veil.patchy
    free = next(m for m in around.weather_models if m.name == "fog-analytic")
    assert free.airlight_logit.requires_grad  # where the photos measure the medium, the airlight learns
    assert around.decisions["fog-analytic patches"].startswith("off: they learn where the views cannot measure β")
    assert not free.patch_log_scale.requires_grad and not free.patchy
    forced = tiny_metegs(
        tmp_path / "forced",
        conditions=conditions,
        max_steps=1,
        clean_supervision=False,
        dark_channel=DarkChannelPriorConfig(mode="on"),
    ).setup()
    assert len(forced.dehazing) == 1 and forced.decisions["dark channel prior"].startswith(
        "on (--dark-channel.mode on)"
    )
    for name, options in (
        ("refs", {}),
        ("off", {"clean_supervision": False, "dark_channel": DarkChannelPriorConfig(weight=0.0)}),
    ):
        other = tiny_metegs(tmp_path / name, conditions=conditions, max_steps=1, **options).setup(scene=rig)
        assert other.dehazing == [] and other.decisions["fog-analytic prior"].startswith("on (weight 0.1)")
        # beside clean references the patches learn too (the references measure the fog); with no measure, not
        assert other.decisions["fog-analytic patches"].startswith("on:" if name == "refs" else "off:")


def test_under_rain_through_fog_a_forward_facing_rig_keeps_the_dark_channel_fog_uniform(tmp_path):
    """Blind under the dark-channel prior, heavy rain through the record's fog: a forward-facing rig sees each point
    from about one distance, where the height profile and the per-view patches take each view's rain light for fog
    (the Ethiopian head), so both stay off; views around the scene (2x apart, the fox's 2.15x) keep them, as does the
    rig in fog alone."""
    from metegs.losses.dark_channel import DarkChannelPriorConfig
    from metegs.weather.medium import MEASURABLE_DISTANCE_SPREAD

    rain_fog = ConditionsConfig(precip_mm_h=20.0, visibility_m=300.0, metres_per_unit=10.0)
    forced = dict(max_steps=1, clean_supervision=False, dark_channel=DarkChannelPriorConfig(mode="on"))
    around = tiny_metegs(tmp_path / "around", conditions=rain_fog, **forced).setup()
    assert around._distance_spread >= MEASURABLE_DISTANCE_SPREAD and len(around.dehazing) == 1
    (fog,) = around.dehazing
    assert around.decisions["fog-analytic layers"].startswith("on:") and fog.height_rate.requires_grad
    assert around.decisions["fog-analytic patches"].startswith("on:") and fog.patch_log_scale.requires_grad
    rig = forward_facing(around.scene)
    facing = tiny_metegs(tmp_path / "facing", conditions=rain_fog, **forced).setup(scene=rig)
    assert facing._distance_spread < MEASURABLE_DISTANCE_SPREAD
    (fog,) = facing.dehazing
    for piece in ("layers", "patches"):
        decision = facing.decisions[f"fog-analytic {piece}"]
        assert decision.startswith("off: heavy rain (20 mm/h) through fog, seen from distances 1.")
        assert decision.endswith("so the fog stays uniform")
    assert not fog.height_rate.requires_grad and not fog.patch_log_scale.requires_grad
    assert not fog.layered and not fog.patchy
    learned = {id(p) for o in facing.method_optimizers.values() for g in o.param_groups for p in g["params"]}
    assert id(fog.height_rate) not in learned and id(fog.patch_log_scale) not in learned
    fog_alone = replace(rain_fog, precip_mm_h=0.0)
    foggy = tiny_metegs(tmp_path / "fog", conditions=fog_alone, **forced).setup(scene=rig)
    assert foggy.decisions["fog-analytic layers"].startswith("on:")
    assert foggy.decisions["fog-analytic patches"].startswith("on:")
    light = tiny_metegs(tmp_path / "light", conditions=replace(rain_fog, precip_mm_h=1.0), **forced).setup(scene=rig)
    assert light.decisions["fog-analytic patches"].startswith("on:")
    refs = tiny_metegs(tmp_path / "refs", conditions=rain_fog, max_steps=1).setup(scene=rig)
    assert refs.decisions["fog-analytic patches"].startswith("on:")  # the references measure the fog


def test_blind_beta_starts_and_stays_at_the_photos_measure_at_the_scene_points(tmp_path):
    """Blind, where the views see the scene's points from distances far apart, the photos' colours there measure β
    (`fit_uniform_medium`): β starts at that measure, the prior holds it there (Gaussians free to take the haze in
    let it drift: the instant-ngp fox in metegs's own 200 m fog, 17.34 dB with β free, 24.16 held at the measure)
    and, as the points read this uniform fog denser upwards, β is one at every height; with clean references β stays
    free."""
    conditions = ConditionsConfig(precip_mm_h=0.0, visibility_m=300.0, metres_per_unit=10.0)
    blind = tiny_metegs(tmp_path / "blind", conditions=conditions, max_steps=1, clean_supervision=False).setup()
    fog = next(m for m in blind.weather_models if m.name == "fog-analytic")
    measured = fog.measured_beta
    assert measured is not None and f"the photos measure β {measured:.2e}/m" in blind.decisions["fog-analytic prior"]
    assert f"explains {blind._measured_medium.explained:.0%} of" in blind.decisions["fog-analytic prior"]
    assert blind._measured_medium.explained > 4 * MIN_MEDIUM_EXPLAINED
    assert fog.use_record_prior and torch.allclose(fog.log_beta.exp().mean(), torch.tensor(measured), rtol=0.05)
    assert float(fog.prior(0).detach()) == 0.0
    with torch.no_grad():
        fog.log_beta += 1.0
    assert float(fog.prior(0).detach()) > 0.0  # held near the measure, not the record
    layers = blind.decisions["fog-analytic layers"]
    assert layers.startswith("off: the points read the fog denser upwards (scale height -") and not fog.layered
    assert fog.summary()["measured_beta_per_m"] == round(measured, 6)
    refs = tiny_metegs(tmp_path / "refs", conditions=conditions, max_steps=1).setup()
    assert refs.decisions["fog-analytic prior"].startswith("off: the views see a scene point from distances")
    assert next(m for m in refs.weather_models if m.name == "fog-analytic").measured_beta is None


def test_blind_beta_learns_in_training_where_the_points_measure_too_thin_a_veil(tmp_path):
    """Clear photos under a record of 300 m fog: at the scene's points a uniform medium explains little of the colour
    differences (`MediumFit.explained`, 2 % here, 39 % in that fog), too little to hold β at that measure (thin veils
    are measured that poorly: the fox's rain veil 1.63e-3/m against 2.45e-3), so β learns in training."""
    conditions = ConditionsConfig(precip_mm_h=0.0, visibility_m=300.0, metres_per_unit=10.0)
    clear = tiny_metegs(tmp_path, conditions=conditions, max_steps=1, clean_supervision=False, degrade="off").setup()
    assert clear._measured_medium.explained < MIN_MEDIUM_EXPLAINED
    fog = next(m for m in clear.weather_models if m.name == "fog-analytic")
    assert not fog.use_record_prior and fog.measured_beta is None and fog.log_beta.requires_grad
    assert "too little to hold β" in clear.decisions["fog-analytic prior"]


def test_blind_the_medium_stays_off_where_the_photos_show_no_veil_of_the_rain(tmp_path):
    """Heavy rain and no visibility in the record: its medium is the rain's veil. Photos without that veil (the clean
    views here; streaks drawn without one cost 8 dB on the built-in scene with a learnt veil) leave it off, as its β
    explains the colours at the scene's points little better than clear air, under an airlight no brighter than the
    scene's middle grey (`veil_evidence`); metegs's own heavy rain,
    which draws the veil, keeps it on, β learning in training (the points' measure of so thin a veil reads 1.7x over),
    and so do clean references, which hold the scene themselves."""
    conditions = ConditionsConfig(precip_mm_h=22.0, visibility_m=None, metres_per_unit=10.0)
    clear = tiny_metegs(tmp_path / "clear", conditions=conditions, max_steps=1, clean_supervision=False, degrade="off")
    clear = clear.setup()
    assert "fog-analytic" not in {m.name for m in clear.weather_models}
    decision = clear.decisions["weather fog-analytic"]
    assert decision.startswith("off: the record gives no visibility") and "show no veil of the rain" in decision
    assert f"under {MIN_AIRLIGHT_OUTSHINES:.0%}" in decision  # the scene's own middle grey read as a veil
    rain = tiny_metegs(tmp_path / "rain", conditions=conditions, max_steps=1, clean_supervision=False, degrade="rain")
    rain = rain.setup()
    assert "fog-analytic" in {m.name for m in rain.weather_models}
    assert rain.decisions["weather fog-analytic"].startswith("on")
    fog = next(m for m in rain.weather_models if m.name == "fog-analytic")
    assert fog.measured_beta is None and fog.log_beta.requires_grad  # a veil that thin learns in training
    assert "too thin for the points' measure" in rain.decisions["fog-analytic prior"]
    refs = tiny_metegs(tmp_path / "refs", conditions=conditions, max_steps=1, degrade="off").setup()
    assert "fog-analytic" in {m.name for m in refs.weather_models}


def test_clean_views_look_into_the_airlight_where_the_scene_is_transparent(trained):
    """Blind training composites the fog's airlight behind the scene; clean renders and evaluation must too,
    else a see-through scene looks dark (a 10 dB loss measured on light rain)."""
    trainer, _ = trained
    fog = next(m for m in trainer.weather_models if m.name == "fog-analytic")
    for training in (True, False):
        assert torch.equal(trainer.background(training), fog.airlight.detach().float())
    i = trainer.dataset.test_indices[0]
    seen, black = trainer.render(i), trainer.render(i, background=torch.zeros(3))  # the configured one is black
    behind = (1.0 - black.alpha)[..., None] * fog.airlight.detach().float()
    assert torch.allclose(seen.rgb - black.rgb, behind, atol=1e-5)


def test_without_fog_the_configured_background_stays(tmp_path):
    trainer = tiny_metegs(tmp_path, weather=("rain-streaks",), max_steps=1).setup()
    assert not any(m.name == "fog-analytic" for m in trainer.weather_models)
    assert torch.equal(trainer.background(False), torch.zeros(3))


def test_resume_restores_weather_and_gtn(trained, tmp_path):
    trainer, _ = trained
    ckpt = trainer.run_dir / "checkpoints" / "step-000040.ckpt"
    again = tiny_metegs(tmp_path, load_checkpoint=ckpt, max_steps=41).setup()
    assert again.step == 40
    for a, b in zip(trainer.gtn.parameters(), again.gtn.parameters()):
        assert torch.equal(a, b)
    fog_a = next(m for m in trainer.weather_models if m.name == "fog-analytic")
    fog_b = next(m for m in again.weather_models if m.name == "fog-analytic")
    assert torch.equal(fog_a.log_beta, fog_b.log_beta)
    again.train()
    assert again.step == 41


def test_a_checkpoint_whose_weather_learned_other_parameters_resumes_with_fresh_moments(tmp_path):
    """A run saved while fewer weather parameters learned (here β uniform in height; or saved by a version before a
    parameter existed) continues: its weather loads, the optimiser's moments of the changed group start afresh,
    said once."""
    from metegs.weather.fog_analytic import FogAnalyticConfig

    conditions = ConditionsConfig(precip_mm_h=0.0, visibility_m=300.0, metres_per_unit=100.0)
    uniform = FogAnalyticConfig(layered=False)
    old = tiny_metegs(tmp_path / "old", conditions=conditions, max_steps=2, checkpoint_every=1, fog_analytic=uniform)
    old = old.setup()
    old.train()
    fog_old = next(m for m in old.weather_models if m.name == "fog-analytic")
    assert not fog_old.layered
    ckpt = old.run_dir / "checkpoints" / "step-000002.ckpt"
    with pytest.warns(UserWarning, match="weather optimiser moments were saved for other learnable parameters"):
        again = tiny_metegs(tmp_path / "new", conditions=conditions, load_checkpoint=ckpt, max_steps=3).setup()
    fog = next(m for m in again.weather_models if m.name == "fog-analytic")
    assert fog.height_rate.requires_grad and torch.equal(fog.log_beta, fog_old.log_beta)
    again.train()
    assert again.step == 3 and float(fog.height_rate.detach()) != 0.0


def test_a_checkpoint_of_another_gtn_width_is_refused_with_the_flag_to_give(trained, tmp_path):
    from metegs.errors import ConfigError

    trainer, _ = trained
    ckpt = trainer.run_dir / "checkpoints" / "step-000040.ckpt"
    width = trainer.config.gtn.width
    with pytest.raises(
        ConfigError, match=f"its GTN is {width} wide, this run's {2 * width}; continue it with --gtn.width {width}"
    ):
        tiny_metegs(tmp_path, load_checkpoint=ckpt, max_steps=41, gtn=GTNConfig(width=2 * width)).setup()


def test_clear_weather_builds_no_weather_and_blind_mode_skips_the_clean_branch(tmp_path):
    config = tiny_metegs(
        tmp_path,
        conditions=ConditionsConfig(precip_mm_h=0.0),
        clean_supervision=False,
        max_steps=2,
        degrade="off",
    )
    trainer = config.setup()
    assert trainer.weather_models == []
    assert trainer.perceptual is None and not trainer.use_clean
    assert "off" in trainer.decisions["weather rain-streaks"] and "off" in trainer.decisions["weather fog-analytic"]
    trainer.train()


def start_colours_and_their_errors(trainer) -> tuple[str, float, float]:
    """(the start-colours decision, mean error of the points' start colours and of the photos' colours against the
    colours the clean references show at the points)."""
    from metegs.data.point_colours import colours_seen
    from metegs.gaussians.sh import sh_to_rgb

    ds, views = trainer.dataset, trainer.dataset.train_indices
    points = trainer.model.params["means"].detach().cpu().numpy()
    cams, depths = ds.cameras[views], [ds.depths[i].numpy() for i in views]
    clean = colours_seen(points, cams, [ds.clean_images[i].numpy() for i in views], depths)
    photos = colours_seen(points, cams, [ds.images[i].numpy() for i in views], depths)
    start = sh_to_rgb(trainer.model.params["sh0"][:, 0].detach()).numpy()
    return trainer.decisions["start colours"], float(abs(start - clean).mean()), float(abs(photos - clean).mean())


@pytest.mark.parametrize("clean_supervision", [False, True])
def test_the_points_start_from_the_scene_without_its_fog(tmp_path, clean_supervision):
    fog = ConditionsConfig(precip_mm_h=0.0, visibility_m=250.0)
    config = tiny_metegs(tmp_path, conditions=fog, degrade="fog", clean_supervision=clean_supervision, max_steps=1)
    decision, start, photos = start_colours_and_their_errors(config.setup())
    assert ("clean references" if clean_supervision else "fog-analytic medium taken out") in decision
    assert start < (0.05 if clean_supervision else 0.7 * photos), (start, photos)
    decision, start, photos = start_colours_and_their_errors(replace(config, clear_start_colours=False).setup())
    assert "photos'" in decision and start == pytest.approx(photos, abs=0.01)  # the degraded copy's colours


def test_extra_points_compensate_sfm_points_only(tmp_path):
    from_points = tiny_metegs(tmp_path / "a", max_steps=2).setup()
    assert not from_points.random_init and from_points.extra_points is not None
    assert from_points.decisions["extra points"].startswith("on")
    at_random = tiny_metegs(
        tmp_path / "b", max_steps=2, model=replace(from_points.config.model, random_init=True)
    ).setup()
    assert at_random.random_init and at_random.extra_points is None
    assert at_random.decisions["init"] == "random Gaussians: --model.random-init"
    assert at_random.decisions["extra points"].startswith("off: the Gaussians started from random points")


def test_eval_of_the_saved_run_reproduces_its_clean_view_metrics(trained):
    from metegs.cli.eval import EvalArgs, main

    trainer, metrics = trained
    m = main(EvalArgs(run_dir=trainer.run_dir, output=trainer.run_dir / "eval-test.json"))
    assert m["reference"] == "clean"
    assert m["psnr"] == pytest.approx(metrics["psnr"], abs=1e-3)


def test_every_registered_weather_model_gets_a_typed_field_and_bad_options_are_named(tmp_path, monkeypatch):
    from dataclasses import dataclass

    from metegs.config import apply_overrides, to_dict
    from metegs.engine.metegs_config import plugin_weather_fields
    from metegs.engine.run import read_config_file
    from metegs.errors import ConfigError
    from metegs.registry import registry
    from metegs.weather.rain_streaks import RainStreaksConfig

    @dataclass
    class HailConfig(RainStreaksConfig):
        """Hail, for this test."""

        stones: int = 7
        """Stones per view."""

    registry("weather").register("hail-stones", HailConfig)
    try:
        cls = plugin_weather_fields(MeteGSConfig)
        assert cls is not MeteGSConfig and issubclass(cls, MeteGSConfig) and plugin_weather_fields(MeteGSConfig) is cls
        config = apply_overrides(cls(), {"hail_stones": {"stones": 9}, "rain_streaks": {"max_count": 123}})
        assert config.weather_config("hail-stones").stones == 9  # from YAML or --hail-stones.stones 9
        assert config.weather_config("rain-streaks").max_count == 123
        assert config.weather_config("fog-analytic") is config.fog_analytic
        assert to_dict(config)["hail_stones"]["stones"] == 9  # config.yml keeps it
        with pytest.raises(ConfigError, match="hail_stones.no_such_field"):
            apply_overrides(cls(), {"hail_stones": {"no_such_field": 1}})
        assert MeteGSConfig().weather_config("hail-stones").stones == 7  # a config without the field: the default
        old = tmp_path / "config.yml"  # a run saved when options were strings under weather_options
        old.write_text("method: metegs-full\nweather_options:\n  rain-streaks: {max_count: 55}\n")
        assert (
            apply_overrides(cls(), {k: v for k, v in read_config_file(old).items() if k != "method"})
            .weather_config("rain-streaks")
            .max_count
            == 55
        )
    finally:
        registry("weather").unregister("hail-stones")
    assert plugin_weather_fields(MeteGSConfig) is MeteGSConfig


def test_a_medium_too_faint_to_see_at_the_scene_depth_is_left_out(tmp_path):
    from metegs.weather.medium import VISIBLE_CONTRAST_LOSS, typical_depth_m, veil_fraction

    def trainer_at(visibility_m, metres_per_unit):
        conditions = ConditionsConfig(precip_mm_h=0.0, visibility_m=visibility_m, metres_per_unit=metres_per_unit)
        return tiny_metegs(tmp_path / f"{visibility_m}-{metres_per_unit}", conditions=conditions, max_steps=1).setup()

    near = trainer_at(2000.0, 1.0)  # the tiny scene is a few units across: 2 km visibility veils ~1 % at its depth
    depth = typical_depth_m(near.dataset.cameras, near.scene.points, 1.0)
    beta = 3.912 / 2000.0 - near.weather_theta(near.scene).fog.beta_background_per_m  # Koschmieder, over clear air
    assert veil_fraction(beta, depth) < VISIBLE_CONTRAST_LOSS
    assert near.decisions["weather fog-analytic"].startswith("off: at β")
    assert not any(m.name == "fog-analytic" for m in near.weather_models)
    far = trainer_at(2000.0, 100.0)  # the same photos said to span hundreds of metres: the veil shows
    assert far.decisions["weather fog-analytic"].startswith("on: the photos' darkest patches show")


def test_typical_depth_is_the_median_distance_of_points_in_front():
    from metegs.testing import camera
    from metegs.weather.medium import typical_depth_m, veil_fraction

    cam = camera()  # at the origin, looking down +z (OpenCV)
    points = torch.tensor([[0.0, 0.0, 2.0], [0.0, 3.0, 4.0], [0.0, 0.0, 9.0], [0.0, 0.0, -5.0]])  # the last is behind
    assert typical_depth_m(cam, points, 10.0) == pytest.approx(50.0)  # median of 2, 5, 9 units, times 10 m
    assert veil_fraction(0.01, 50.0) == pytest.approx(1 - torch.exp(torch.tensor(-0.5)).item())
    assert veil_fraction(0.0, 50.0) == 0.0


def test_light_rain_switches_off_the_gtn_and_the_robust_mask_and_blind_training_the_gtn(tmp_path):
    light = tiny_metegs(tmp_path / "light", conditions=ConditionsConfig(precip_mm_h=1.5), max_steps=1).setup()
    assert light.gtn is None and light.decisions["gtn"].startswith("off: light rain")
    assert light.robust_from is None and light.decisions["robust mask"].startswith("off: light rain")
    heavy = tiny_metegs(tmp_path / "heavy", max_steps=1).setup()  # 20 mm/h and 400 m: blur and bright streaks
    assert heavy.gtn is not None and heavy.decisions["gtn"].startswith("on")
    # blind, nothing holds the scene's sharpness: the GTN stays off unless asked for
    blind = tiny_metegs(tmp_path / "blind", clean_supervision=False, max_steps=1).setup()
    assert blind.gtn is None and blind.decisions["gtn"].startswith("off: blind training")
    assert "gtn" not in blind.method_optimizers
    asked = tiny_metegs(tmp_path / "asked", clean_supervision=False, max_steps=1, gtn=GTNConfig(blind=True)).setup()
    assert asked.gtn is not None and asked.decisions["gtn"].startswith("on")
    off = tiny_metegs(tmp_path / "off", max_steps=1, gtn=GTNConfig(enabled=False)).setup()
    assert off.gtn is None and off.decisions["gtn"] == "off"
    assert heavy.robust_from is not None and heavy.decisions["robust mask"].startswith("on")


def test_heavy_rain_fits_a_low_quantile_of_the_photos(tmp_path):
    """Rain only adds light: the trimmed L1 fits a low quantile of a pixel's photos in heavy rain, the median where
    the user asks for it, a milder one where the dark-channel prior holds the medium, and nothing changes in light
    rain (no mask)."""

    heavy = tiny_metegs(tmp_path / "heavy", max_steps=1).setup()  # 20 mm/h and 400 m
    assert heavy.robust_from is not None and heavy.quantile == 0.1
    assert heavy.decisions["low-quantile fit"].startswith("on: the trimmed L1 fits the 10% quantile")
    # blind from random points the dark-channel prior holds the medium, whose veil takes some of the rain's light
    dark = tiny_metegs(
        tmp_path / "dark",
        max_steps=1,
        clean_supervision=False,
        model=replace(heavy.config.model, random_init=True),
    ).setup()
    assert dark.dehazing and dark.robust_from is not None and dark.quantile == 0.25
    assert "25%, not 10%: the dark-channel prior holds the medium" in dark.decisions["low-quantile fit"]
    forced = tiny_metegs(
        tmp_path / "forced",
        max_steps=1,
        clean_supervision=False,
        model=replace(heavy.config.model, random_init=True),
        robust=record_robust(quantile=0.1),
    ).setup()
    assert forced.dehazing and forced.quantile == 0.1
    median = tiny_metegs(tmp_path / "median", robust=record_robust(quantile=0.5), max_steps=1).setup()
    assert median.robust_from is not None and median.decisions["low-quantile fit"].startswith("off: --robust.quantile")
    light = tiny_metegs(tmp_path / "light", conditions=ConditionsConfig(precip_mm_h=1.5), max_steps=1).setup()
    assert light.robust_from is None and "low-quantile fit" not in light.decisions
    losses = []
    for trainer in (heavy, median):  # same seed, same start: only the quantile tells the two losses apart
        trainer.step = trainer.robust_from
        index, background = trainer.dataset.train_indices[0], trainer.background(training=True)
        with torch.no_grad():
            render = trainer.photo_render(index, background)
            losses.append(float(trainer.step_loss(index, background, render, trainer.target(index, background), {})))
    assert losses[0] != pytest.approx(losses[1], rel=1e-3)


def test_the_quantile_is_chosen_from_how_the_photos_spread_about_a_point(tmp_path, monkeypatch):
    """Blind of the clear scene, at `robust_from` the run reads how the photos of the surfaces it renders spread about
    each point's median (`view_spread`): far above it (streaks reach few of a point's views) the L1 fits the median,
    about evenly the low quantile, a quantile between them in between, and with too few points the low quantile stays; a resumed run keeps the choice
    without measuring again."""
    import metegs.engine.metegs_trainer as trainer_module
    from metegs.eval.view_spread import ViewSpread

    def chosen(name: str, spread: ViewSpread, **kw):
        monkeypatch.setattr(trainer_module, "view_spread", lambda *a, **k: spread)
        trainer = tiny_metegs(tmp_path / name, max_steps=1, **kw).setup()
        assert (
            trainer.quantile == 0.1
            and "until step 0, where the photos' spread" in trainer.decisions["low-quantile fit"]
        )
        trainer.step = trainer.robust_from
        index, background = trainer.dataset.train_indices[0], trainer.background(training=True)
        with torch.no_grad():
            render = trainer.photo_render(index, background)
            trainer.step_loss(index, background, render, trainer.target(index, background), {})
        return trainer

    sparse = chosen("sparse", ViewSpread(5000, 0.05, 0.12))
    said = sparse.decisions["low-quantile fit"]
    assert sparse.quantile == 0.5 and sparse.stroke_width == 1
    assert said.startswith("off: at 5000 points seen by 6 or more views the photos spread 2.40 times as far above")
    dense = chosen("dense", ViewSpread(5000, 0.1, 0.11))
    assert dense.quantile == 0.1 and dense.decisions["low-quantile fit"].startswith("on: the trimmed L1 fits the 10%")
    assert "spread 1.10 times as far above" in dense.decisions["low-quantile fit"]
    between = chosen("between", ViewSpread(5000, 0.1, 0.16))
    assert (
        between.quantile == 0.3
        and "between 1.2 and 2: the streaks reach only some" in between.decisions["low-quantile fit"]
    )
    few = chosen("few", ViewSpread(12, 0.05, 0.12))
    assert few.quantile == 0.1 and "12 points seen by 6 or more views, too few" in few.decisions["low-quantile fit"]
    # the user's quantile is never measured over
    monkeypatch.setattr(trainer_module, "view_spread", lambda *a, **k: pytest.fail("measured"))
    asked = tiny_metegs(tmp_path / "asked", max_steps=1, robust=record_robust(quantile=0.1)).setup()
    assert not asked._quantile_pending and "until step" not in asked.decisions["low-quantile fit"]

    monkeypatch.setattr(trainer_module, "view_spread", lambda *a, **k: ViewSpread(5000, 0.05, 0.12))
    first = tiny_metegs(tmp_path / "first", max_steps=20).setup()
    first.train()
    saved = json.loads((first.run_dir / "decisions.json").read_text())["decisions"]["low-quantile fit"]
    assert saved == first.decisions["low-quantile fit"] and saved.startswith("off: at 5000 points")  # made in training
    monkeypatch.setattr(trainer_module, "view_spread", lambda *a, **k: pytest.fail("measured again"))
    ckpt = first.run_dir / "checkpoints" / "step-000020.ckpt"
    again = tiny_metegs(tmp_path / "again", max_steps=21, load_checkpoint=ckpt).setup()
    assert again.quantile == 0.5 and again.decisions["low-quantile fit"] == first.decisions["low-quantile fit"]
    again.train()
    assert again.step == 21


def test_heavy_rain_the_photos_do_not_show_is_not_trimmed(tmp_path):
    """The record's heavy rain turns the robust mask and the low-quantile fit on only where the training photos show
    streaks (`stroke_energy` at least `RobustMaskConfig.min_stroke_energy`), and the decision says which: the tiny
    scene under metegs's own 20 mm/h (faint streaks, which its rain model explains) keeps every pixel, the same
    scene under the independent family's streak layers trims them."""
    from metegs.losses.robust import VISIBLE_STROKE_ENERGY, RobustMaskConfig, stroke_energy

    scene = DatasetConfig(synthetic=SyntheticSceneConfig(width=160, height=120, num_views=12, num_points=600))
    options = dict(max_steps=1, robust=RobustMaskConfig(), dataset=scene, degrade="rain")
    faint = tiny_metegs(tmp_path / "faint", **options).setup()
    energy = faint._photos_stroke_energy()
    views = faint.dataset.train_indices
    assert energy == pytest.approx(float(np.median([stroke_energy(faint.dataset.images[i]) for i in views])))
    assert energy < VISIBLE_STROKE_ENERGY
    assert faint.robust_from is None and faint.quantile == 0.5 and "low-quantile fit" not in faint.decisions
    assert faint.decisions["robust mask"].startswith("off: the photos do not show the streaks of heavy rain")
    assert f"{energy:.4f} of energy" in faint.decisions["robust mask"]
    shown = tiny_metegs(tmp_path / "shown", degrade_family="independent", **options).setup()
    assert shown._photos_stroke_energy() > VISIBLE_STROKE_ENERGY
    assert shown.robust_from is not None and "as the photos show streaks" in shown.decisions["robust mask"]
    assert shown.decisions["low-quantile fit"].startswith("on")
    record = tiny_metegs(tmp_path / "record", **{**options, "robust": record_robust()}).setup()  # the record decides
    assert record.robust_from is not None and "photos show" not in record.decisions["robust mask"]


def test_a_medium_the_photos_do_not_show_is_left_out(tmp_path):
    """The record's medium is on only where the training photos' darkest patches show at least `min_photo_veil` of
    veil (the median `photo_veil` over the training views); where they show less the decision gives the value, and
    per-view exposure is decided as in 3dgs. The tiny scene's grey ground never reads clear, so the bar is moved
    to either side of what its fogged photos show."""
    from metegs.eval.veil import photo_veil

    fogged = tiny_metegs(tmp_path / "fogged", max_steps=1).setup()
    (fog,) = [m for m in fogged.weather_models if isinstance(m, FogAnalytic)]
    veil = fogged._photos_veil(fog.airlight.detach())
    views = fogged.dataset.train_indices
    assert veil == pytest.approx(float(np.median([photo_veil(fogged.dataset.images[i], fog.airlight) for i in views])))
    assert veil > MeteGSConfig().min_photo_veil
    assert fogged.decisions["weather fog-analytic"] == f"on: the photos' darkest patches show {veil:.1%} of veil"
    assert fogged.has_medium and fogged.decisions["view_exposure"].startswith("off (a fog model is on")
    clear = tiny_metegs(tmp_path / "clear", max_steps=1, min_photo_veil=min(1.0, veil + 0.05)).setup()
    decision = clear.decisions["weather fog-analytic"]
    assert decision.startswith("off: the record's β") and f"show {veil:.1%} of veil" in decision
    assert not clear.has_medium and clear.medium_optical_depth == 0.0
    assert "a fog model is on" not in clear.decisions["view_exposure"]  # as 3dgs decides it
    assert "dark channel prior" not in clear.decisions and clear.decisions["weather rain-streaks"].startswith("on")
    record = tiny_metegs(tmp_path / "record", max_steps=1, min_photo_veil=0.0).setup()
    assert record.has_medium and record.decisions["weather fog-analytic"] == "on"


def test_the_ssim_weight_of_the_low_quantile_fit_is_its_own(tmp_path):
    """D-SSIM asks for the photos' streaky local contrast, which a fit held under the photos makes by darkening the
    gaps between the streaks (dark strokes in the fox's clean render): while the L1 fits the low quantile, the
    weather branch's loss takes `RobustMaskConfig.ssim_lambda` where it is set; with the median the loss's own."""
    from metegs.losses.robust import RobustMaskConfig

    def run(name: str, **robust) -> tuple[float, str]:
        """(the weather branch's loss once the low-quantile fit is on, the decision `low-quantile fit`)."""
        trainer = tiny_metegs(tmp_path / name, robust=record_robust(**robust), max_steps=1).setup()
        trainer.step = trainer.robust_from
        index, background = trainer.dataset.train_indices[0], trainer.background(training=True)
        with torch.no_grad():
            render = trainer.photo_render(index, background)
            loss = trainer.step_loss(index, background, render, trainer.target(index, background), {})
        return float(loss), trainer.decisions["low-quantile fit"]

    own = PhotometricLossConfig().ssim_lambda
    assert RobustMaskConfig().ssim_lambda is None
    runs = {lam: run(f"low{lam}", ssim_lambda=lam) for lam in (0.0, 0.05, own)}
    low = {lam: loss for lam, (loss, _) in runs.items()}
    assert "D-SSIM at weight 0.05" in runs[0.05][1]
    unset, said = run("unset")
    assert unset == pytest.approx(low[own]) and "D-SSIM at weight" not in said
    assert low[0.0] != pytest.approx(low[0.05], rel=1e-4) and low[0.05] != pytest.approx(low[own], rel=1e-4)
    # the loss is linear in the weight: (1 − λ)·L1 + λ·(1 − SSIM), the priors beside it unchanged
    assert low[0.05] == pytest.approx(low[0.0] + (low[own] - low[0.0]) * 0.05 / own, rel=1e-4)
    median = run("median", quantile=0.5, ssim_lambda=0.0)[0]
    assert median == pytest.approx(run("median2", quantile=0.5)[0], rel=1e-6)


def test_the_low_quantile_fit_takes_bright_strokes_out_of_ssim(tmp_path):
    """`RobustMaskConfig.stroke_px`: while the L1 fits the low quantile, D-SSIM compares render and photo without the
    bright strokes narrower than that width scaled to the image (the photo's streaks are not asked of the render),
    and the decision says so; where that width is under 2 px, and with the L1 fitting the median, they are compared
    as they are."""
    from metegs.losses.robust import STROKE_REFERENCE_SIDE_PX, RobustMaskConfig, inlier_weights, without_bright_strokes

    def run(name: str, **robust):
        trainer = tiny_metegs(tmp_path / name, robust=record_robust(**robust), max_steps=1).setup()
        trainer.step = trainer.robust_from
        index, background = trainer.dataset.train_indices[0], trainer.background(training=True)
        with torch.no_grad():
            render = trainer.photo_render(index, background)
            target = trainer.target(index, background)
            loss = float(trainer.step_loss(index, background, render, target, {}))
        return trainer, render.rgb, target, loss

    three_px = 3.0 * STROKE_REFERENCE_SIDE_PX / 64  # the tiny scene is 64 px wide
    taken, rgb, target, loss = run("taken", stroke_px=three_px)
    assert taken.stroke_width == 3
    assert "without the bright strokes under 3 px wide" in taken.decisions["low-quantile fit"]
    scaled, *_ = run("scaled", stroke_px=3.0)  # 3 px at 480 px: under a pixel at 64
    assert scaled.stroke_width == 1 and "under 2 px wide at 64 px" in scaled.decisions["low-quantile fit"]
    assert RobustMaskConfig().stroke_px == 3  # on by default, 3 px at 480 px
    plain, rgb0, _, loss0 = run("plain", stroke_px=0.0)
    assert "strokes" not in plain.decisions["low-quantile fit"] and torch.equal(rgb, rgb0)
    pair = without_bright_strokes(rgb, target, 3, taken.config.robust.min_excess)
    assert not torch.equal(pair[1], target)  # the tiny scene's rain has thin bright strokes
    # the priors are the same (same seed): the losses differ by photo · λ · (D-SSIM of the pair without strokes −
    # D-SSIM of the pair as it is), each over the inliers
    weights = inlier_weights(target - rgb, taken.config.robust)
    loss_fn, lam = taken.loss_fn, taken.config.loss.ssim_lambda
    d_ssim = [loss_fn(rgb, target, weights, ssim_lambda=1.0, ssim_images=images) for images in (pair, None)]
    assert loss - loss0 == pytest.approx(taken.config.weights.photo * lam * float(d_ssim[0] - d_ssim[1]), rel=1e-3)
    assert loss != pytest.approx(loss0, rel=1e-5)
    median = run("median", quantile=0.5, stroke_px=three_px)
    assert median[3] == pytest.approx(run("median2", quantile=0.5, stroke_px=0.0)[3], rel=1e-6)


def test_sharp_weather_prunes_opacity_as_3dgs_does(tmp_path):
    """Light rain with no visible medium blurs nothing: the faint Gaussians MeteGS keeps for blurred photos only fit
    single views there (1.1 dB under 3dgs on the Lund street), so training takes 3dgs's threshold and says so; a
    threshold the user chose stays, and heavy rain keeps MeteGS's, unless, blind, the photos show no medium: streaks
    over a clear view blur nothing either."""
    from metegs.engine.metegs_config import BLURRED_PRUNE_OPACITY, SHARP_PRUNE_OPACITY

    assert SHARP_PRUNE_OPACITY > BLURRED_PRUNE_OPACITY
    drizzle, default = ConditionsConfig(precip_mm_h=1.5), MeteGSConfig().densify
    light = tiny_metegs(tmp_path / "light", conditions=drizzle, max_steps=3000, densify=default).setup()
    assert light.densifier.config.prune_opacity == SHARP_PRUNE_OPACITY
    assert light.decisions["opacity pruning"].startswith(f"{SHARP_PRUNE_OPACITY:g} (3dgs's): light rain")
    chosen = replace(default, prune_opacity=0.02)
    mine = tiny_metegs(tmp_path / "mine", conditions=drizzle, max_steps=3000, densify=chosen).setup()
    assert mine.densifier.config.prune_opacity == 0.02 and "opacity pruning" not in mine.decisions
    heavy = tiny_metegs(tmp_path / "heavy", max_steps=3000, densify=default).setup()  # 20 mm/h and 400 m
    assert heavy.densifier.config.prune_opacity == BLURRED_PRUNE_OPACITY and "opacity pruning" not in heavy.decisions
    # blind, heavy rain whose photos show no veil: streaks over a clear view, which blur nothing of the scene
    storm, blind = ConditionsConfig(precip_mm_h=20.0), dict(clean_supervision=False, densify=default, max_steps=3000)
    clear = tiny_metegs(tmp_path / "clear", conditions=storm, min_photo_veil=1.0, **blind).setup()
    assert not clear.has_medium and clear.densifier.config.prune_opacity == SHARP_PRUNE_OPACITY
    assert "no visible medium: streaks over a clear view" in clear.decisions["opacity pruning"]
    veiled = tiny_metegs(tmp_path / "veiled", conditions=storm, min_photo_veil=0.0, **blind).setup()
    assert veiled.has_medium and veiled.densifier.config.prune_opacity == BLURRED_PRUNE_OPACITY


def test_sharp_weather_trains_as_3dgs_does(tmp_path):
    """Blind, in light rain with no visible medium: no learnable streaks, GTN, extra points, depth-aware pruning or
    camera clearance (on the Lund street the first four cost 0.2-0.55 dB against 3dgs there and left no cleaner
    render), so the run is 3dgs's, step for step; heavy rain, or clean references, keep all but the streaks, which
    only clean references keep."""
    from metegs.engine.compare import baseline_config
    from metegs.engine.trainer import Trainer

    quiet = dict(max_steps=60, eval_every=0.0, save_renders=False, checkpoint_every=0, clean_supervision=False)
    light = tiny_metegs(tmp_path / "light", conditions=ConditionsConfig(precip_mm_h=1.5), **quiet)
    light = replace(light, densify=MeteGSConfig().densify).setup()
    assert light.weather_models == [] and light.gtn is None and light.extra_points is None
    for key in ("weather rain-streaks", "extra points", "depth pruning", "camera clearance"):
        assert light.decisions[key].startswith("off: light rain (1.5 mm/h) and no visible medium"), key
    base = Trainer(baseline_config(light.config), run_dir=tmp_path / "base", scene=light.scene)
    for trainer in (light, base):  # one after the other, from one seed: splitting draws from torch's generator
        torch.manual_seed(0)
        order = trainer._view_order()
        while trainer.step < trainer.config.max_steps:
            trainer.train_step(next(order))
            trainer.step += 1
    assert len(light.model) == len(base.model) > 0
    for name, value in base.model.params.items():
        assert torch.equal(light.model.params[name], value), name
    heavy = tiny_metegs(tmp_path / "heavy", max_steps=3000, densify=MeteGSConfig().densify).setup()  # 20 mm/h
    # beside clean references they pay in light rain too (built-in scene, 1.5 mm/h: 37.22 dB with, 36.47 without)
    refs = tiny_metegs(tmp_path / "refs", conditions=ConditionsConfig(precip_mm_h=1.5), max_steps=3000).setup()
    for trainer in (heavy, refs):
        assert trainer.decisions["weather rain-streaks"].startswith("on") and trainer.extra_points is not None
        assert trainer.decisions["depth pruning"].startswith("on")
    # blind in heavy rain: the extra points and depth pruning stay, the learnable streaks never train blind
    from metegs.engine.metegs_trainer import BLIND_STREAKS

    blind = tiny_metegs(tmp_path / "blind", max_steps=3000, densify=MeteGSConfig().densify, clean_supervision=False)
    blind = blind.setup()
    assert blind.decisions["weather rain-streaks"] == f"off: {BLIND_STREAKS}"
    assert not any(isinstance(m, LearnableTransients) for m in blind.weather_models)
    assert blind.extra_points is not None and blind.decisions["depth pruning"].startswith("on")


def test_opacity_resets_are_off_only_where_blind_training_regrows_under_the_fog(tmp_path):
    """Resets remove the Gaussians that fitted single photos' streaks (measured on two real captures): where it
    rains under thin fog the plain 3DGS schedule stays; blind, under fog alone, or fog dense at the scene's depth
    (visibility under 3× it) over an SfM cloud, the fog-dimmed gradients hardly regrow what a reset takes, and they are
    off. Beside clean references, whose gradients no fog dims, they stay on and say so."""
    from metegs.densify.adc import AdaptiveDensityControl
    from metegs.engine.metegs_trainer import DENSE_OPTICAL_DEPTH

    rain = tiny_metegs(tmp_path / "rain", max_steps=3000, densify=ADCConfig(), clean_supervision=False).setup()
    assert "opacity reset" not in rain.decisions  # 20 mm/h and 400 m
    assert 0 < rain.medium_optical_depth < DENSE_OPTICAL_DEPTH
    plain = AdaptiveDensityControl(ADCConfig(), 3000, rain.extent, len(rain.dataset.train_indices))
    assert rain.densifier.reset_every == plain.reset_every > 0
    dense = ConditionsConfig(precip_mm_h=20.0, visibility_m=100.0, wind_speed_m_s=4.0, wind_dir_deg=90.0)
    fog = ConditionsConfig(precip_mm_h=0.0, visibility_m=300.0, metres_per_unit=100.0)
    blind = {}
    for name, conditions, why in (("storm", dense, "off: the medium's optical depth"), ("fog", fog, "off: no rain")):
        config = tiny_metegs(
            tmp_path / name, max_steps=3000, densify=ADCConfig(), conditions=conditions, clean_supervision=False
        )
        blind[name] = config.setup()
        assert blind[name].gtn is None and blind[name].densifier.reset_every == 0, name  # the rule follows the weather
        assert blind[name].decisions["opacity reset"].startswith(why), name
        refs = replace(config, clean_supervision=True, output_dir=tmp_path / f"{name}-refs").setup()
        assert refs.use_clean and refs.gtn is not None and refs.densifier.reset_every == plain.reset_every, name
        assert refs.decisions["opacity reset"].startswith("on: the clean references"), name
        assert why[5:] in refs.decisions["opacity reset"], name  # the blind rule it overrides, named
    assert blind["storm"].medium_optical_depth >= DENSE_OPTICAL_DEPTH
    # from random points resets clear their floaters, also in dense fog
    storm = blind["storm"].config
    floaters = replace(storm, model=replace(storm.model, random_init=True), output_dir=tmp_path / "random")
    assert "opacity reset" not in floaters.setup().decisions


def test_view_exposure_auto_is_off_beside_a_fog_model_and_3dgs_s_rule_without(tmp_path):
    """Beside a fog model its airlight and β set each view's tone; without one (light rain) MeteGS learns each
    photo's tone as 3dgs does (3dgs's rule: off for a rendered scene such as this one, on for photos)."""
    foggy = tiny_metegs(tmp_path / "fog", max_steps=5).setup()  # 20 mm/h and 400 m: fog-analytic on
    assert foggy.has_medium and foggy.exposure is None
    assert foggy.decisions["view_exposure"].startswith("off (a fog model is on")
    light = tiny_metegs(tmp_path / "light", max_steps=5, conditions=ConditionsConfig(precip_mm_h=1.5)).setup()
    assert not light.has_medium and light.decisions["view_exposure"].startswith("off (a rendered scene")
    forced = tiny_metegs(tmp_path / "on", max_steps=5, view_exposure="on").setup()
    assert forced.has_medium and forced.exposure is not None


def test_view_exposure_on_takes_each_photo_s_tone_in_both_branches(tmp_path):
    trainer = tiny_metegs(tmp_path, view_exposure="on", max_steps=5, eval_every=0.0, save_renders=False).setup()
    assert trainer.exposure is not None and tiny_metegs(tmp_path).view_exposure == "auto"
    i = trainer.dataset.train_indices[0]
    with torch.no_grad():
        trainer.exposure.offsets[0, 0] += 0.5  # view i's gains up (the other views' down by the mean)
    bg = trainer.background(training=True)
    with torch.no_grad():
        weather = trainer.render_weather(i, bg, training=True).rgb
        photo = trainer.photo_render(i, bg).rgb
        clean = trainer.clean_branch(i, bg)
        settings = RenderSettings(background=bg, sh_degree=trainer.model.active_sh_degree)
        scene = trainer.rasterizer.render(trainer.model.activated(), trainer.dataset.cameras[i], settings)
    gains, offsets = trainer.exposure.gains_and_offsets()
    assert torch.allclose(photo, weather * gains[0] + offsets[0], atol=1e-5)
    # the clean reference is the same photo without the weather: the clean branch takes its tone too
    assert torch.allclose(clean, scene.rgb * gains[0] + offsets[0], atol=1e-5)
    trainer.train()
    assert float(trainer.exposure.offsets.detach().abs()[:, 1].sum()) > 0  # the offsets learned from the photos


def test_pseudo_references_hold_a_blind_clean_branch_to_the_restored_photos(tmp_path):
    from metegs.losses.photometric import box_detail
    from metegs.restore import restorer_for_kinds

    config = tiny_metegs(tmp_path, clean_supervision=False, pseudo_references="restore", max_steps=3)
    trainer = config.setup()
    assert trainer.active_kinds >= {"rain", "fog"}
    assert trainer.decisions["pseudo references"].startswith("on: the clean branch's detail (x - its 15-px box mean)")
    assert "held to the 10 training photos" in trainer.decisions["pseudo references"]
    assert "(0 read from" in trainer.decisions["pseudo references"]
    # a second run restores nothing: the photos come from the cache, the same to the bit
    again = config.setup()
    assert "(10 read from" in again.decisions["pseudo references"]
    assert all(torch.equal(again.pseudo_references[i], trainer.pseudo_references[i]) for i in trainer.pseudo_references)
    assert set(trainer.pseudo_references) == set(trainer.dataset.train_indices)
    i = trainer.dataset.train_indices[0]
    expected = restorer_for_kinds("rain+fog").restore(trainer.dataset.images[i].numpy())
    assert torch.allclose(trainer.pseudo_references[i], torch.from_numpy(expected))
    assert (trainer.pseudo_references[i] - trainer.dataset.images[i]).abs().mean() > 0.01  # restoring changed it
    # the term is the weighted L1 of the clean branch's detail against the restored photo's: blind to their tone
    with torch.no_grad():
        clean = trainer.clean_branch(i, trainer.background(training=True))
    reference = trainer.pseudo_references[i]
    l1 = (box_detail(clean, 15) - box_detail(reference, 15)).abs().mean()
    assert torch.allclose(loss_term(trainer, i, "pseudo"), 0.5 * l1, atol=1e-6)
    trainer.pseudo_references[i] = reference + 0.2  # a brighter restoration, the same detail: the same term
    assert torch.allclose(loss_term(trainer, i, "pseudo"), 0.5 * l1, atol=1e-5)
    trainer.pseudo_references[i] = reference
    trainer.config.pseudo_detail_px = 0  # the whole photo: its colours count too
    assert torch.allclose(loss_term(trainer, i, "pseudo"), 0.5 * (clean - reference).abs().mean(), atol=1e-6)
    trainer.config.pseudo_detail_px = 15
    trainer.train()


def loss_term(trainer, index: int, weight: str) -> torch.Tensor:
    """What the term of loss weight ``weight`` (a `LossWeights` field) adds to view ``index``'s step loss."""
    weights, bg = trainer.config.weights, trainer.background(training=True)
    render, kept = trainer.photo_render(index, bg), getattr(weights, weight)
    with torch.no_grad():
        held = trainer.step_loss(index, bg, render, trainer.target(index, bg), {})
        setattr(weights, weight, 0.0)
        free = trainer.step_loss(index, bg, render, trainer.target(index, bg), {})
    setattr(weights, weight, kept)
    return held - free


def test_clean_references_hold_the_clean_branch_with_the_photo_loss(tmp_path):
    # with references the clean branch is trained as 3dgs trains on clean photos: L1 + SSIM, at twice the photos'
    # weight (an L1 at 0.1 left the built-in default 1.5 dB under 3dgs on its clean photos)
    from metegs.engine.metegs_config import LossWeights
    from metegs.losses.photometric import PhotometricLossConfig

    trainer = tiny_metegs(tmp_path, weights=LossWeights(perceptual=0.0), max_steps=3).setup()
    assert trainer.use_clean and trainer.config.weights.clean == 2.0
    assert trainer.decisions["clean branch"].startswith("on: 3dgs's L1 + SSIM")
    i, bg = trainer.dataset.train_indices[0], trainer.background(training=True)
    with torch.no_grad():
        clean, reference = trainer.clean_branch(i, bg), trainer.reference(i, bg)
        l1 = (clean - reference).abs().mean()
        expected = PhotometricLossConfig(ssim_lambda=trainer.config.loss.ssim_lambda).setup()(clean, reference)
    term = loss_term(trainer, i, "clean")
    assert torch.allclose(term, 2.0 * expected, atol=1e-6)
    # the SSIM term counts: the term is more than the L1 part alone
    assert float(term) > 2.1 * float((1 - trainer.config.loss.ssim_lambda) * l1)


def test_densification_reads_the_clean_branch_where_clean_references_hold_it(tmp_path):
    # with the photo's weight at 0 only the clean branch moves the scene, so only its screen-space gradients can
    # reach the densification statistics; the weather branch's alone left the head under rain + fog with a third
    # fewer Gaussians than 3dgs on its clean photos
    from metegs.engine.metegs_config import LossWeights

    for clean_supervision, reads in ((True, 2), (False, 1)):
        trainer = tiny_metegs(
            tmp_path / str(clean_supervision), weights=LossWeights(photo=0.0, perceptual=0.0),
            clean_supervision=clean_supervision, max_steps=3,
        ).setup()  # fmt: skip
        trainer.train_step(trainer.dataset.train_indices[0])
        state = trainer.densifier.state
        assert int(state.count.max()) == reads  # one read per render of the scene: weather branch (and clean)
        assert (float(state.grad_sum.sum()) > 0) == clean_supervision


def test_pseudo_references_stay_off_where_clean_references_hold_the_clean_branch(tmp_path):
    trainer = tiny_metegs(tmp_path, pseudo_references="restore", max_steps=3).setup()
    assert trainer.pseudo_references == {}
    assert trainer.decisions["pseudo references"].startswith("off: the clean references")


def test_a_perceptual_loss_without_weights_is_said_once_as_a_warning(tmp_path, monkeypatch):
    """Clean references ask for the perceptual term; with no weights anywhere (and no download) the run says why it
    is off in one warning line, the decision itself, not twice."""
    from rich.console import Console

    from metegs.losses.perceptual import PERCEPTUAL_ENV, PerceptualLossConfig

    hub = torch.hub.get_dir()
    torch.hub.set_dir(str(tmp_path / "hub"))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.delenv(PERCEPTUAL_ENV, raising=False)
    console = Console(record=True, width=1000)
    try:
        config = tiny_metegs(tmp_path, perceptual=PerceptualLossConfig(download=False), max_steps=2)
        trainer = config.setup(console=console)
    finally:
        torch.hub.set_dir(hub)
    decision = trainer.decisions["perceptual"]
    assert trainer.use_clean and trainer.perceptual is None and decision.startswith("off: ")
    text = console.export_text()
    assert text.count(decision[len("off: ") :]) == 1, text
    assert f"warning: perceptual: {decision}" in text


def test_gaussians_at_the_training_cameras_are_gone_when_training_ends(tmp_path):
    from metegs.densify.camera_clearance import unseen_near_cameras
    from metegs.densify.surgery import append_rows

    trainer = tiny_metegs(tmp_path, max_steps=3, checkpoint_every=0, eval_every=0.0).setup()
    assert trainer.decisions["camera clearance"].startswith("on: Gaussians within")
    cameras = trainer.dataset.cameras[trainer.dataset.train_indices]
    centers = cameras.camera_to_worlds[:, :3, 3].float()
    radius = trainer.clearance.radius
    scene = len(trainer.model)
    assert not unseen_near_cameras(trainer.model.means.detach(), cameras, radius).any()  # the scene keeps its distance
    floaters = {k: v.detach()[: len(centers)].clone() for k, v in trainer.model.params.items()}
    floaters["means"] = centers - 0.2 * radius * cameras.camera_to_worlds[:, :3, 2]  # just behind each camera
    append_rows(trainer.model.params, trainer.optimizers, floaters)
    assert int(unseen_near_cameras(trainer.model.means.detach(), cameras, radius).sum()) == len(centers)
    trainer.train()
    assert not unseen_near_cameras(trainer.model.means.detach(), cameras, radius).any()
    assert len(trainer.model) >= scene - 50  # the rest stays (3 steps of densification may prune a few)
    off = tiny_metegs(tmp_path / "off", max_steps=1, camera_clearance=0.0).setup()
    assert off.clearance is None and off.decisions["camera clearance"] == "off"


def test_the_robust_mask_trims_only_the_photos_thin_strokes(tmp_path):
    """Where streaks are two pixels wide or more, only the photo's thin bright strokes may be trimmed (found once per
    view and said in the decision); `thin_only` off, or smaller images, let any outlier go."""
    from metegs.losses.robust import thin_strokes

    big = DatasetConfig(synthetic=SyntheticSceneConfig(width=320, height=240, num_views=4, num_points=300))
    trainer = tiny_metegs(tmp_path / "big", dataset=big).setup()
    assert trainer.thin_width == 5 and "bright strokes under 5 px wide" in trainer.decisions["robust mask"]
    view = int(trainer.dataset.train_indices[0])
    strokes = trainer._thin_strokes(view)
    assert strokes.dtype == torch.bool and strokes.shape == trainer.dataset.images[view].shape[:2]
    assert torch.equal(strokes, thin_strokes(trainer.dataset.images[view], 5, trainer.config.robust.min_excess))
    assert trainer._thin_strokes(view) is strokes  # once per view
    anything = tiny_metegs(tmp_path / "any", dataset=big, robust=record_robust(thin_only=False)).setup()
    assert anything._thin_strokes(view) is None and "bright strokes" not in anything.decisions["robust mask"]
    assert tiny_metegs(tmp_path / "small").setup()._thin_strokes(view) is None  # 64 px: streaks under 2 px
