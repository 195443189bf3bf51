"""Plug-ins named by import path: ``package.module:attribute``.

Schedulers, scenarios and channel profiles are found by a registered name or by such a
path (docs/extending.md); each caller turns ``PluginError`` into its own error type.
"""

from __future__ import annotations

import importlib
from typing import Any


class PluginError(LookupError):
    """An import path that does not load."""


def is_import_path(name: object) -> bool:
    return isinstance(name, str) and ":" in name


def load(path: str) -> Any:
    """The attribute at ``package.module:attribute``; ``PluginError`` says why not."""
    module, _, attr = path.partition(":")
    try:
        return getattr(importlib.import_module(module), attr)
    except (ImportError, AttributeError) as exc:
        raise PluginError(f"cannot load {path!r}: {exc}") from None
