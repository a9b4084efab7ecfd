"""Optional native components of a backend (a compiled extension, an imported CUDA library): loaded once per
process on first use; a failure is remembered with its reason and reported by one warning."""

from __future__ import annotations

import threading
import warnings
from collections.abc import Callable
from typing import Any


class OptionalComponent:
    """Loads ``build()`` once. ``load`` raises ``error_type`` (the reason kept) when it cannot be had;
    ``available`` answers False instead, warning once with ``warning_type`` that ``fallback`` is used."""

    def __init__(
        self,
        build: Callable[[], Any],
        describe_failure: Callable[[Exception], str],
        error_type: type[Exception],
        warning_type: type[Warning],
        fallback: str,
    ):
        self._build = build
        self._describe = describe_failure
        self.error_type = error_type
        self.warning_type = warning_type
        self.fallback = fallback
        self.value: Any = None
        """The loaded component (None until loaded)."""
        self.error: str | None = None
        """Why it could not be loaded (None if it was not tried or it worked)."""
        self.warned = False
        self._lock = threading.Lock()

    def load(self) -> Any:
        """The component, loading it on first use."""
        if self.value is not None:
            return self.value
        with self._lock:
            if self.value is None:
                if self.error is not None:
                    raise self.error_type(self.error)
                try:
                    self.value = self._build()
                except Exception as exc:  # noqa: BLE001 - any failure means "not available", with the reason kept
                    self.error = self._describe(exc)
                    raise self.error_type(self.error) from exc
        return self.value

    def available(self) -> bool:
        """True once loaded; False (with one warning per process) when it cannot be."""
        try:
            self.load()
        except self.error_type as exc:
            if not self.warned:
                self.warned = True
                warnings.warn(f"{exc}; {self.fallback}", self.warning_type, stacklevel=3)
            return False
        return True
