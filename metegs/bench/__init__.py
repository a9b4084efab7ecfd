"""Benchmarks: rasteriser speed (`raster`) and, later, method suites."""
