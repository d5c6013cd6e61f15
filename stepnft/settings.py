"""Settings declared once, checked from their declaration.

Every config dataclass (the run's sections in ``stepnft.config``, the algorithm configs, SFT's,
the policy's ``config.json``, the command configs) derives from :class:`Settings`. A field's type
says what it accepts; ``Annotated`` adds a range::

    lr: Annotated[float, Range(gt=0)] = 1e-4
    \"\"\"AdamW learning rate of the policy.\"\"\"

One checker, :func:`check_fields`, reads these types whenever a config is built: from Python,
a YAML file, flags or a saved policy's ``config.json``.

==================  ===========================================================================
declared type       accepted value
==================  ===========================================================================
``int``             an int (not a bool, not a float)
``float``           an int or a float, finite (stored as a float)
``bool``            True or False
``str``             a string
``Literal[...]``    one of its values: the choices are never listed again
``X | None``        None or an X (``X | Y``: the first arm that takes the value)
``list[str]``       names: a string or strings, each comma-separated (``stepnft.names``)
``tuple[X, Y]``     a sequence of as many values, each checked (stored as a tuple)
``dict[str, X]``    a mapping of strings to Xs
a dataclass         an instance of it (a nested section)
==================  ===========================================================================

``Range(gt=, ge=, lt=, le=)`` bounds a number, and every number has an upper bound the work can
honour (a test walks every settings class for it), so a huge value is refused with its flag's name
before anything is allocated for it; the bounds several settings share are declared below
(``SEED_MAX``, ``EVAL_SEEDS_END``, ``ITERATIONS_MAX``, ``WIDTH_MAX``, ``DEMO_EPISODES_MAX``). ``Check(predicate, description)`` states any other
rule of one value. Rules between fields are a config's :meth:`Settings.check`. A bad value is a
:class:`SettingError` that names the setting the way the user wrote it: ``algo.lr`` (YAML) or
``--algo.lr`` (flags). This module is a low layer: it imports nothing of stepnft but names.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import re
import types
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, ClassVar, Literal, Union

from stepnft.names import split_names

SEED_MAX = 2**31 - 1
"""The largest run seed (``seed``, ``demos.seed``): every generator it reaches takes it (numpy,
torch, MuJoCo's and ManiSkill's RandomState, which stop at 2**32), offsets included."""
EVAL_SEEDS_END = 2**24
"""Evaluation initial states (test and validation, ``eval.seed + e``) have seeds below this;
training episodes' reset seeds start here (``stepnft.rollout.plan.TRAINING_SEEDS``), so the two
never meet."""
ITERATIONS_MAX = 10**8
"""The most RL iterations a run (and any setting counted in iterations) may name."""
WIDTH_MAX = 16384
"""The widest layer or feature vector a policy or critic may declare (a 16k x 16k layer is 1 GiB
of float32 weights)."""
SETTINGS_FILE_BYTES_MAX = 1 << 20
"""The largest settings file read (a YAML config, a policy's config.json): 1 MiB, against a few
kilobytes for a real one, so a huge file is refused before it is read."""
DEMO_EPISODES_MAX = 2**20
"""Demonstration attempts per task: attempt k of seed s resets from ``2**32 + s * 2**20 + k``
(``stepnft.data.demos.demo_seed``), so more would reuse another seed's initial states."""


@dataclass(frozen=True)
class Range:
    """Bounds of a number: ``gt < x``, ``ge <= x``, ``x < lt``, ``x <= le`` (None: unbounded)."""

    gt: float | None = None
    ge: float | None = None
    lt: float | None = None
    le: float | None = None

    def accepts(self, x: float) -> bool:
        return ((self.gt is None or x > self.gt) and (self.ge is None or x >= self.ge)
                and (self.lt is None or x < self.lt) and (self.le is None or x <= self.le))

    def __str__(self) -> str:
        low = f"[{_number(self.ge)}" if self.ge is not None else f"({_number(self.gt)}" if self.gt is not None else None
        high = f"{_number(self.le)}]" if self.le is not None else f"{_number(self.lt)})" if self.lt is not None else None
        if low and high:
            return f"in {low}, {high}"
        if low:
            return f"{'>=' if low[0] == '[' else '>'} {low[1:]}"
        return f"{'<=' if high[-1] == ']' else '<'} {high[:-1]}" if high else ""


def _number(x: float) -> str:
    """A bound as written: integral ones exactly (``2147483647``), others short (``1e-06``)."""
    return str(int(x)) if float(x).is_integer() and abs(x) < 1e15 else f"{x:g}"


@dataclass(frozen=True)
class Check:
    """A rule of one value that is not a range: ``predicate(value)`` must hold; ``description``
    says what is allowed (it replaces the type's own description in messages)."""

    predicate: Callable[[Any], bool]
    description: str

    def accepts(self, value: Any) -> bool:
        return self.predicate(value)


class SettingError(ValueError):
    """A bad setting. ``template`` names settings as ``{key}``, relative to ``section``;
    ``str()`` writes them as YAML keys (``algo.lr``), :meth:`as_flags` as flags (``--algo.lr``).
    ``got``, when given, is appended as ``, got VALUE``."""

    _KEY = re.compile(r"\{([a-z][a-z0-9_.]*)\}")
    _NOTHING = object()

    def __init__(self, template: str, section: str = "", got: Any = _NOTHING):
        self.template, self.section = template, section
        self.got = "" if got is self._NOTHING else f", got {got!r}"
        super().__init__(self._render(lambda key: key))

    def _render(self, spell: Callable[[str], str]) -> str:
        def full(match: re.Match) -> str:
            return spell(f"{self.section}.{match[1]}" if self.section else match[1])

        return self._KEY.sub(full, self.template) + self.got

    def as_flags(self) -> str:
        """The message with every setting named by its command-line flag."""
        return self._render(lambda key: "--" + key.replace("_", "-"))


def read_settings_text(path: str | Path, what: str = "config file") -> str:
    """The text of settings file ``path``; a ValueError with one line when it is larger than
    :data:`SETTINGS_FILE_BYTES_MAX` (checked before reading) or not UTF-8."""
    path = Path(path)
    size = path.stat().st_size
    if size > SETTINGS_FILE_BYTES_MAX:
        raise ValueError(f"{what} {path} is {size} bytes: settings files are at most {SETTINGS_FILE_BYTES_MAX} "
                         "bytes (is it the right file?)")
    try:
        return path.read_text()
    except UnicodeDecodeError:
        raise ValueError(f"{what} {path} is not UTF-8 text (is it the right file?)") from None


class Settings:
    """Base of every config dataclass: built -> every field checked against its declared type
    (:func:`check_fields`) -> :meth:`check`, the rules between fields."""

    section: ClassVar[str] = ""
    """Where the fields sit in a run's config (``algo`` for ``algo.lr``); "" at the top."""

    def __post_init__(self) -> None:
        check_fields(self)
        self.check()

    def check(self) -> None:
        """Rules between fields (a subclass adds its own; raise :class:`SettingError`)."""

    def fail(self, template: str, got: Any = SettingError._NOTHING) -> SettingError:
        """A :class:`SettingError` about this config's fields (``{lr}`` names ``algo.lr``)."""
        return SettingError(template, self.section, got)


def check_fields(obj) -> None:
    """Check every field of dataclass ``obj`` against its declared type (module doc) and store
    the normalised values; a :class:`SettingError` names the first bad one."""
    hints = _type_hints(type(obj))
    section = getattr(obj, "section", "")
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        try:
            checked = _checked(value, hints[f.name])
        except _Mismatch:
            raise SettingError(f"{{{f.name}}} must be {describe(hints[f.name])}", section, value) from None
        object.__setattr__(obj, f.name, checked)


def describe(hint) -> str:
    """What a declared type accepts, in words (``a finite number > 0``)."""
    hint, rules = _unwrap(hint)
    checks = [r for r in rules if isinstance(r, Check)]
    if checks:
        return checks[0].description
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    bounds = "".join(f" {r}" for r in rules if isinstance(r, Range))
    if origin in (Union, types.UnionType):
        arms = [describe(a) for a in args if a is not type(None)]
        return " or ".join(arms) + bounds + (" or None" if type(None) in args else "")
    if origin is Literal:
        return "one of " + ", ".join(map(str, args))
    if origin is list:
        return "a list of names" if args[0] is str else f"a list of values, each {describe(args[0])}"
    if origin is tuple:
        parts = [describe(a) for a in args]
        return f"{len(parts)} values, each {parts[0]}" if len(set(parts)) == 1 else f"({', '.join(parts)})"
    if origin is dict:
        return f"a mapping of names to values, each {describe(args[1])}"
    words = {int: "an integer", float: "a finite number", bool: "true or false", str: "a string"}
    return words.get(hint, f"a {getattr(hint, '__name__', hint)}") + bounds


class _Mismatch(Exception):
    """A value that does not fit its declared type (reported for the whole field)."""


@functools.lru_cache(maxsize=None)
def _type_hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls, include_extras=True)


def _unwrap(hint) -> tuple[Any, tuple]:
    """``Annotated[T, *rules]`` -> ``(T, rules)``; any other type -> ``(type, ())``."""
    if typing.get_origin(hint) is typing.Annotated:
        return hint.__origin__, hint.__metadata__
    return hint, ()


def _checked(value, hint):
    """``value`` normalised to ``hint`` (see the module doc); raises _Mismatch."""
    hint, rules = _unwrap(hint)
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        arms = [a for a in args if a is not type(None)]
        for arm in arms[:-1]:  # the first arm that takes the value (``bool | int | str``: in that order)
            try:
                return _checked(value, arm)
            except _Mismatch:
                pass
        value = _checked(value, arms[-1])
    elif origin is Literal:
        _require(any(type(value) is type(a) and value == a for a in args))
    elif origin is list and args[0] is str:
        _require(isinstance(value, str) or (isinstance(value, (list, tuple)) and all(isinstance(v, str) for v in value)))
        value = split_names(value)
    elif origin is list:
        _require(isinstance(value, (list, tuple)))
        value = [_checked(v, args[0]) for v in value]
    elif origin is tuple:
        _require(isinstance(value, (list, tuple)) and len(value) == len(args))
        value = tuple(_checked(v, a) for v, a in zip(value, args))
    elif origin is dict:
        _require(isinstance(value, dict))
        value = {_checked(k, args[0]): _checked(v, args[1]) for k, v in value.items()}
    else:
        value = _checked_scalar(value, hint)
    _require(all(rule.accepts(value) for rule in rules))
    return value


def _checked_scalar(value, hint):
    if hint is float:
        _require(isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value))
        return float(value)
    if hint is int:
        _require(isinstance(value, int) and not isinstance(value, bool))
    elif hint in (bool, str) or dataclasses.is_dataclass(hint):
        _require(isinstance(value, hint))
    else:
        raise TypeError(f"stepnft.settings cannot check settings of type {hint!r}")
    return value


def _require(condition: bool) -> None:
    if not condition:
        raise _Mismatch
