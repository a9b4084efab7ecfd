"""The fog medium measured at a degraded scene's SfM points, against the one its generator drew.

    python benchmarks/medium_at_points.py outputs/bench/real/lund/rain+fog-ind/data   # a metegs-bench data folder

A scene point of colour J seen through fog at distance d shows I = J·t + A·(1 − t), t = exp(−τ(d)). Where the views
see the points from distances far apart (a street walked down), I changes from view to view by the medium alone, so
the photos' colours at the points' projections measure β, its fall with height and the airlight A with one unknown
J per point. Training measures the same through the scene's Gaussians, which can take the haze in themselves
(Gaussians near the cameras, colours that change with the view): on OpenSfM's Lund street under independent height
fog, blind training let β fall to a third of the generator's while this fit comes within 10 %. Views that do not
see a point (occlusion, a wall in between) and rain streaks over it are outliers of a robust loss. A diagnostic, not
part of the method: held at this fit, blind MeteGS did not gain (docs/benchmark.md, the Lund street).
"""

from __future__ import annotations

import argparse
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from metegs.cameras import Cameras
from metegs.weather.fog_analytic import height_profile

FIT_STEPS = 1500
"""Adam steps of the fit."""


@dataclass
class PointObservations:
    """Colours the photos show at scene points, with the geometry of each observation (one row each)."""

    point: torch.Tensor
    """[N] long, index of the observed point."""
    colour: torch.Tensor
    """[N, 3] the photo's colour at the point's projection (median of 3×3 pixels)."""
    distance_m: torch.Tensor
    """[N] camera-to-point distance, metres."""
    camera_height_m: torch.Tensor
    """[N] the camera's height over the cameras' mean, metres."""
    rise: torch.Tensor
    """[N] height gained per metre along the ray to the point."""

    def __len__(self) -> int:
        return len(self.point)


@dataclass
class MediumFit:
    """β at the cameras' mean height, its height rate and the airlight that explain the photos at the points."""

    beta_per_m: float
    height_rate: float
    """100·k, ln β's fall per 100 m of height (`FogAnalytic.height_rate`)."""
    airlight: tuple[float, float, float]
    observations: int
    points: int

    def describe(self) -> str:
        k = self.height_rate / 100.0
        height = "uniform" if abs(k) < 1e-6 else f"scale height {1.0 / k:.0f} m"
        a = ", ".join(f"{v:.2f}" for v in self.airlight)
        return (
            f"β {self.beta_per_m:.2e}/m ({height}), airlight ({a}), fitted to {self.observations} observations of "
            f"{self.points} points"
        )


def sample_median3(image: torch.Tensor, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Median over the 3×3 pixels around integer pixels (x [N], y [N]) of image [H, W, 3] -> [N, 3]."""
    h, w = image.shape[:2]
    offsets = torch.tensor([-1, 0, 1], device=image.device)
    xs = (x[:, None, None] + offsets[None, None, :]).clamp(0, w - 1)
    ys = (y[:, None, None] + offsets[None, :, None]).clamp(0, h - 1)
    patch = image[ys, xs].reshape(len(x), 9, 3)
    return patch.median(dim=1).values


def point_observations(
    cameras: Cameras,
    images: list[torch.Tensor],
    points: torch.Tensor,
    up: torch.Tensor,
    metres_per_unit: float,
    max_points: int = 4096,
) -> PointObservations:
    """Every projection of ``points`` [P, 3] (at most ``max_points``, evenly spread) inside the frame of each view
    of ``cameras`` (images [H, W, 3] at the cameras' sizes), in front of it: occlusion is not known here and is left
    to the fit's robust loss. ``up`` [3] world up."""
    pts = torch.as_tensor(points, dtype=torch.float32).cpu()
    pts = pts[:: max(1, len(pts) // max_points)]
    cameras = cameras.to("cpu")
    up = (up.float() / up.float().norm()).cpu()
    centres = cameras.centers.float()
    reference = (centres @ up).mean()
    w2c = cameras.world_to_cameras().float()
    rows: dict[str, list[torch.Tensor]] = {k: [] for k in ("point", "colour", "distance", "height", "rise")}
    for v, image in enumerate(images):
        cam = pts @ w2c[v, :3, :3].T + w2c[v, :3, 3]
        z = cam[:, 2]
        front = z > 1e-6
        x = cam[:, 0] / z.clamp_min(1e-6) * cameras.fx[v] + cameras.cx[v]
        y = cam[:, 1] / z.clamp_min(1e-6) * cameras.fy[v] + cameras.cy[v]
        h, w = image.shape[:2]
        inside = front & (x >= 0) & (x < w) & (y >= 0) & (y < h)
        idx = torch.nonzero(inside).squeeze(1)
        if len(idx) == 0:
            continue
        offset = pts[idx] - centres[v]
        distance = offset.norm(dim=-1).clamp_min(1e-12)
        rows["point"].append(idx)
        rows["colour"].append(sample_median3(image.detach().float().cpu(), x[idx].long(), y[idx].long()))
        rows["distance"].append(distance * metres_per_unit)
        rows["height"].append(torch.full_like(distance, float(centres[v] @ up - reference) * metres_per_unit))
        rows["rise"].append((offset @ up) / distance)
    cat = {k: torch.cat(v) if v else torch.zeros(0) for k, v in rows.items()}
    return PointObservations(
        point=cat["point"].long(),
        colour=cat["colour"].reshape(-1, 3),
        distance_m=cat["distance"],
        camera_height_m=cat["height"],
        rise=cat["rise"],
    )


def fit_medium(obs: PointObservations, beta_start: float, layered: bool = True, steps: int = FIT_STEPS) -> MediumFit:
    """Robust least squares (Charbonnier) of I = J·t + A·(1 − t) over ``obs``, t = exp(−β·d·`height_profile`), for β
    (from ``beta_start``), the height rate (0 unless ``layered``), A and one J per point."""
    points = int(obs.point.max()) + 1 if len(obs) else 0
    log_beta = torch.tensor(math.log(beta_start), requires_grad=True)
    height_rate = torch.zeros((), requires_grad=layered)
    airlight_logit = torch.full((3,), 1.5, requires_grad=True)
    scene_logit = torch.zeros((points, 3), requires_grad=True)
    params = [log_beta, airlight_logit, scene_logit] + ([height_rate] if layered else [])
    opt = torch.optim.Adam(params, lr=0.02)
    for _ in range(steps):
        k = height_rate / 100.0
        tau = log_beta.exp() * obs.distance_m * height_profile(k, obs.camera_height_m, obs.rise, obs.distance_m)
        t = torch.exp(-tau)[:, None]
        predicted = torch.sigmoid(scene_logit[obs.point]) * t + torch.sigmoid(airlight_logit) * (1.0 - t)
        loss = torch.sqrt((predicted - obs.colour) ** 2 + 1e-4).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    airlight = torch.sigmoid(airlight_logit.detach())
    return MediumFit(
        beta_per_m=float(log_beta.detach().exp()),
        height_rate=float(height_rate.detach()),
        airlight=(float(airlight[0]), float(airlight[1]), float(airlight[2])),
        observations=len(obs),
        points=len(torch.unique(obs.point)) if len(obs) else 0,
    )


def generator_medium(data: Path, scene) -> dict | None:
    """The independent generator's β at the cameras' mean height (green channel), scale height and airlight, from
    ``data``/weather.json (None for other families)."""
    from metegs.weather.independent import ground_height

    record = json.loads((data / "weather.json").read_text())
    fog = next((v["fog"] for v in record.get("views", []) if "fog" in v), None)
    if fog is None:
        return None
    up = np.asarray(scene.up, np.float64) / np.linalg.norm(scene.up)
    centres = scene.cameras.camera_to_worlds[:, :3, 3].double().numpy()
    height_m = ((centres @ up).mean() - ground_height(scene, up)) * record["metres_per_unit"]
    beta = fog["beta_per_m"] * fog["channel_scale"][1] * math.exp(-max(height_m, 0.0) / fog["scale_height_m"])
    return {"beta_per_m": beta, "scale_height_m": fog["scale_height_m"], "airlight": fog["airlight"]}


def main() -> None:
    from metegs.data.config import DatasetConfig
    from metegs.data.images import load_image
    from metegs.data.parsers.base import parse_scene

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "data", type=Path, help="a degraded scene folder with weather.json (metegs-synth, metegs-bench)"
    )
    args = parser.parse_args()
    scene = parse_scene(args.data, None, DatasetConfig())
    if scene.points is None:
        raise SystemExit(f"{args.data}: the scene has no points to measure the medium at")
    mpu = json.loads((args.data / "weather.json").read_text())["metres_per_unit"]
    views = scene.train_indices
    images = [torch.from_numpy(load_image(scene.image_paths[i])) for i in views]
    obs = point_observations(
        scene.cameras[views], images, torch.as_tensor(scene.points), torch.as_tensor(scene.up), mpu
    )
    for layered in (False, True):
        print(("layered: " if layered else "uniform: ") + fit_medium(obs, 0.01, layered=layered).describe())
    truth = generator_medium(args.data, scene)
    if truth is not None:
        a = ", ".join(f"{v:.2f}" for v in truth["airlight"])
        print(
            f"generator: β {truth['beta_per_m']:.2e}/m at the cameras' mean height (green), scale height "
            f"{truth['scale_height_m']:.0f} m, airlight ({a}) before its view-dependent factor 0.85-1"
        )


if __name__ == "__main__":
    main()
