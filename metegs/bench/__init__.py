"""Benchmarks: rasteriser speed (`raster`), training steps (`step`) and method suites (`suite`).

Suites (`metegs-bench SUITE.yaml`): `suite_config` (the YAML), `conditions` (weather picked from real
records), `data` (degraded and restored photos, cached), `suite` (the resumable runner), `report` and `plot`
(tables in the paper's layout, PSNR-vs-time PNGs).
"""
