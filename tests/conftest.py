"""Test session settings."""

import os

import torch

if os.environ.get("PYTEST_XDIST_WORKER"):
    # Each xdist worker gets one thread: torch's OpenMP threads busy-wait, and two workers with two
    # threads each on a 2-core machine slow each other down many times over.
    torch.set_num_threads(1)

if "METEGS_EXTENSIONS_DIR" not in os.environ:
    # Tests that point $XDG_CACHE_HOME at a temporary folder must not build the kernels again there (about 50 s
    # each): the build stays in the cache this session found (tests of the folder's choice unset this).
    from metegs.render.cpu_backend import build_directory

    os.environ["METEGS_EXTENSIONS_DIR"] = str(build_directory())

import pytest  # noqa: E402


@pytest.fixture(autouse=True)
def _restore_flush_denormal():
    """The trainer turns on flush-to-zero for the process (a speed-up); tests that use it must not leak it
    into later tests (hypothesis refuses to run when subnormal floats cannot be represented)."""
    yield
    torch.set_flush_denormal(False)


@pytest.fixture(autouse=True, scope="session")
def _no_downloads():
    """Tests never download: weights that product code would fetch on first use (the torch hub cache) fail as they
    do offline, with a reason; tests that need weights pass local files explicitly. Session-wide, so that module
    fixtures that train are covered too."""

    def offline(url, *args, **kwargs):
        raise OSError(f"tests never download ({url})")

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(torch.hub, "load_state_dict_from_url", offline)
        patch.setattr(torch.hub, "download_url_to_file", offline)
        yield


@pytest.fixture(autouse=True)
def _fresh_failed_downloads(monkeypatch):
    """Each test starts without the memory of earlier tests' failed downloads."""
    from metegs.eval import backbones

    monkeypatch.setattr(backbones, "FAILED_DOWNLOADS", {})


@pytest.fixture(autouse=True)
def _private_restored_cache(monkeypatch, tmp_path_factory):
    """Photos restored by tests (pseudo-references, the suite's restoration baseline) go to a folder of the test's,
    never into the user's cache."""
    from metegs.restore import cache

    folder = tmp_path_factory.mktemp("restored")
    monkeypatch.setattr(cache, "restored_cache_dir", lambda: folder)


PLUGINS = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "plugins")
"""The example plugin packages (plugins/)."""


def plugin_from_source(monkeypatch, package: str, module: str):
    """Rediscover plugins with an example plugin importable from ``plugins/<package>/src`` and named by
    ``METEGS_PLUGINS=<module>`` (as without installing it); yields, then restores the registries."""
    import sys

    import metegs.registry as reg

    reg.ensure_plugins_loaded()  # the built-ins register once per process: have them in what is restored
    saved = {k: dict(r._entries) for k, r in reg._REGISTRIES.items()}
    monkeypatch.syspath_prepend(os.path.join(PLUGINS, package, "src"))
    monkeypatch.setenv("METEGS_PLUGINS", module)
    monkeypatch.setattr(reg, "failed_plugins", {})
    monkeypatch.setitem(reg._plugins_state, "loaded", False)
    sys.modules.pop(module, None)
    yield
    sys.modules.pop(module, None)
    for k, r in reg._REGISTRIES.items():
        r._entries = saved[k]


@pytest.fixture
def snow_plugin(monkeypatch):
    """The example snow plugin (plugins/metegs-snow), loaded from its sources."""
    yield from plugin_from_source(monkeypatch, "metegs-snow", "metegs_snow.register")


@pytest.fixture
def idr_plugin(monkeypatch):
    """The example IDR/NeuS parser plugin (plugins/metegs-parser-idr), loaded from its sources."""
    yield from plugin_from_source(monkeypatch, "metegs-parser-idr", "metegs_parser_idr.register")
