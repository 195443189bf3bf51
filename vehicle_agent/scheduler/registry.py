"""Schedulers by name, so an agent picks one from its configuration.

A scheduler is any function ``(instance, state) -> Schedule`` that is deterministic
in its inputs. Register one with ``@register("name", "alias")``; or name it as
``"package.module:function"`` and ``get`` imports it, so a user's scheduler needs no
change to the agent at all.
"""

from __future__ import annotations

from collections.abc import Callable

from protocol import plugins
from vehicle_agent.scheduler.instance import Instance, Schedule
from vehicle_agent.scheduler.state import SchedulerState

SchedulerFn = Callable[[Instance, SchedulerState], Schedule]

_SCHEDULERS: dict[str, SchedulerFn] = {}


class UnknownSchedulerError(LookupError):
    """A scheduler name that is neither registered nor an importable ``module:function``."""


def register(name: str, *aliases: str) -> Callable[[SchedulerFn], SchedulerFn]:
    """Decorator: make ``fn`` available as ``get(name)`` and ``get(alias)``."""

    def wrap(fn: SchedulerFn) -> SchedulerFn:
        for key in (name, *aliases):
            if key in _SCHEDULERS and _SCHEDULERS[key] is not fn:
                raise ValueError(f"scheduler name {key!r} is already registered")
            _SCHEDULERS[key] = fn
        return fn

    return wrap


def names() -> tuple[str, ...]:
    """Every registered name and alias, sorted."""
    return tuple(sorted(_SCHEDULERS))


def get(name: str) -> SchedulerFn:
    """The scheduler registered as ``name``, or the callable at ``"module:function"``."""
    fn = _SCHEDULERS.get(name)
    if fn is not None:
        return fn
    if plugins.is_import_path(name):
        try:
            fn = plugins.load(name)
        except plugins.PluginError as e:
            raise UnknownSchedulerError(str(e)) from None
        if not callable(fn):
            raise UnknownSchedulerError(f"scheduler {name!r} is not callable")
        return fn
    raise UnknownSchedulerError(f"unknown scheduler {name!r}; known: {', '.join(names())} (or 'module:function')")
