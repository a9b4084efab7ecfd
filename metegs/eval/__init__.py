"""Image-quality evaluation: PSNR, SSIM and LPIPS.

- `metegs.eval.metrics`: `psnr`, `ssim` / `ssim_map` (differentiable, separable Gaussian window, also
  used as the training D-SSIM loss) and `evaluate_images` (per-view metrics averaged over views).
- `metegs.eval.lpips`: LPIPS v0.1 (AlexNet / VGG16 backbone defined here, torchvision-compatible
  checkpoints, official linear heads) with explicit weight resolution; `WeightsUnavailable` is raised
  (or `(None, reason)` returned by `try_load_lpips`) when weights are missing: no substitute metric
  is ever reported under the name LPIPS.
"""
