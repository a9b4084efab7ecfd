"""Test session settings."""

import os

import torch

if os.environ.get("PYTEST_XDIST_WORKER"):
    # Each xdist worker gets one thread: torch's OpenMP threads busy-wait, and two workers with two
    # threads each on a 2-core machine slow each other down many times over.
    torch.set_num_threads(1)


import pytest  # noqa: E402


@pytest.fixture(autouse=True)
def _restore_flush_denormal():
    """The trainer turns on flush-to-zero for the process (a speed-up); tests that use it must not leak it
    into later tests (hypothesis refuses to run when subnormal floats cannot be represented)."""
    yield
    torch.set_flush_denormal(False)


@pytest.fixture(autouse=True)
def _no_downloads(monkeypatch):
    """Tests never download: weights that product code would fetch on first use (the torch hub cache) fail as they
    do offline, with a reason; tests that need weights pass local files explicitly."""

    def offline(url, *args, **kwargs):
        raise OSError(f"tests never download ({url})")

    monkeypatch.setattr(torch.hub, "load_state_dict_from_url", offline)
    monkeypatch.setattr(torch.hub, "download_url_to_file", offline)
    from metegs.eval import backbones

    monkeypatch.setattr(backbones, "FAILED_DOWNLOADS", {})


SNOW_SRC = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "plugins", "metegs-snow", "src")
"""The example snow plugin's sources (plugins/metegs-snow/src)."""


@pytest.fixture
def snow_plugin(monkeypatch):
    """Rediscover plugins with the example snow plugin importable from its source folder (through ``METEGS_PLUGINS``,
    as without installing it); the registries are restored after."""
    import sys

    import metegs.registry as reg

    reg.ensure_plugins_loaded()  # the built-ins register once per process: have them in what is restored
    saved = {k: dict(r._entries) for k, r in reg._REGISTRIES.items()}
    monkeypatch.syspath_prepend(SNOW_SRC)
    monkeypatch.setenv("METEGS_PLUGINS", "metegs_snow.register")
    monkeypatch.setattr(reg, "failed_plugins", {})
    monkeypatch.setitem(reg._plugins_state, "loaded", False)
    sys.modules.pop("metegs_snow.register", None)
    yield
    sys.modules.pop("metegs_snow.register", None)
    for k, r in reg._REGISTRIES.items():
        r._entries = saved[k]
