"""Plugins: simulators, policies and algorithms of other packages, found by entry point.

A package adds one line per part to its ``pyproject.toml``, and stepnft needs no edit::

    [project.entry-points."stepnft.simulators"]
    mysim = "my_pkg.sim:INFO"            # a stepnft.envs.SimulatorInfo (its target: "my_pkg.sim:MySim")
    [project.entry-points."stepnft.policies"]
    mypolicy = "my_pkg.policy:MyPolicy"  # a stepnft.policies.base.Policy subclass (its saved ``type``)
    [project.entry-points."stepnft.algorithms"]
    myalgo = "my_pkg.algo:MyAlgo"        # a stepnft.algos.base.Algorithm subclass (``algo.name``)
    [project.entry-points."stepnft.variants"]
    myalgo-fast = "my_pkg.algo:FAST"     # a stepnft.algos.variants.Variant (``stepnft compare --algos``)

The registries (``stepnft.envs.SIMULATORS``, ``stepnft.policies.base.POLICY_TYPES``,
``stepnft.algos.base.ALGORITHMS``, ``stepnft.algos.variants.VARIANTS``) keep their names and
their values' types; each is a :class:`PluginRegistry` that merges its group's entry points on
its first lookup, in every process that looks (Ray workers and torchrun ranks look names up too,
so they see the same plugins). Policies and algorithms stay lazy (``module:Class`` strings,
imported on first use); a simulator's or a variant's entry point is loaded at once, since the
config checks its facts (episode length, tasks; a variant's algorithm) before anything is built. A plugin whose name is taken, or whose simulator entry point
fails to load, is a :class:`PluginError`: one line naming its package.
"""

from __future__ import annotations

from importlib.metadata import entry_points
from typing import Any, Callable

GROUPS = ("stepnft.simulators", "stepnft.policies", "stepnft.algorithms", "stepnft.variants")
"""The entry-point groups stepnft reads."""


class PluginError(ValueError):
    """A plugin that cannot be registered (a name taken, an entry point that fails to load)."""


def _package(ep) -> str:
    dist = getattr(ep, "dist", None)
    return f"package {dist.name}" if dist is not None else f"entry point {ep.value}"


class PluginRegistry(dict):
    """A registry dict (name -> value) that adds group ``group``'s entry points on first lookup.
    ``load``: True to store the loaded object (simulators), False to store ``ep.value``, the
    ``module:Class`` string (policies, algorithms). ``check`` validates a loaded object."""

    def __init__(self, group: str, builtin: dict[str, Any], load: bool = False,
                 check: Callable[[Any], str | None] | None = None):
        super().__init__(builtin)
        self.group, self.load, self.check, self._merged = group, load, check, False
        self.sources = {name: "stepnft" for name in builtin}
        """Which package registered each name."""

    def _merge(self) -> None:
        if self._merged:
            return
        self._merged = True  # first: a plugin that looks names up while it loads sees the built-ins
        for ep in sorted(entry_points(group=self.group), key=lambda e: (e.name, e.value)):
            where = _package(ep)
            if dict.__contains__(self, ep.name):
                raise PluginError(f"{self.group} plugin {ep.name!r} of {where} is already registered by "
                                  f"{self.sources[ep.name]}: rename it in that package's pyproject.toml")
            value: Any = ep.value
            if self.load:
                try:
                    value = ep.load()
                except Exception as err:  # the plugin's own code: say whose, in one line
                    raise PluginError(f"{self.group} plugin {ep.name!r} of {where} fails to load "
                                      f"({type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''})") from None
                problem = self.check(value) if self.check else None
                if problem:
                    raise PluginError(f"{self.group} plugin {ep.name!r} of {where}: {problem}")
            elif ":" not in value:
                raise PluginError(f"{self.group} plugin {ep.name!r} of {where} names {value!r}: it must be "
                                  "'module:Class'")
            dict.__setitem__(self, ep.name, value)
            self.sources[ep.name] = where

    # Every read merges first; writes (a test adding a name) too, so the plugins are never lost.
    def __getitem__(self, key):
        self._merge()
        return super().__getitem__(key)

    def __contains__(self, key):
        self._merge()
        return super().__contains__(key)

    def __iter__(self):
        self._merge()
        return super().__iter__()

    def __len__(self):
        self._merge()
        return super().__len__()

    def __setitem__(self, key, value):
        self._merge()
        super().__setitem__(key, value)
        self.sources[key] = "set in code"

    def get(self, key, default=None):
        self._merge()
        return super().get(key, default)

    def keys(self):
        self._merge()
        return super().keys()

    def items(self):
        self._merge()
        return super().items()

    def values(self):
        self._merge()
        return super().values()

    def __repr__(self):
        self._merge()
        return super().__repr__()
