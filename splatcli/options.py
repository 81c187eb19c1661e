"""Options declared once, at the config field they set.

Each field of a config dataclass carries its option in its metadata (`opt`): the help
text, the range or choices it must lie in, and, when it is on the command line, the
`--help` heading it goes under. A nested config is a `section`. `table(ConfigClass)`
flattens such a tree into named options; `apply`, `value` and `check` use it, `load`
reads a stored (nested) config back, and the CLI builds its Typer options from the same
table (cli/options.py). Nothing else lists the options. Taking options by name (`parse`, once, into a `Given`)
is the command line's edge alone (cli/train_config.py): the code past it reads and edits the
typed fields.

Names: an option is named after its field, after the section's `prefix` when it has one
(`compact_keep`, `mcmc_shrink`); the command line writes it as `--compact-keep`. A section
may apply only when a choice has a value (`when=("strategy", "mcmc")`): the fields it
shares with the other alternatives (`shared`, declared once in the base class they have
in common: a strategy's schedule and budget) are named without the prefix and set the
alternative that is chosen; an option of an alternative that is not chosen is an error.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import types
import typing
from collections.abc import Callable
from dataclasses import dataclass, field, fields, replace
from typing import Any

from .errors import SplatError

# The `--help` headings, in the order `train --help` shows them.
SCHEDULE = "Schedule"
DATA = "Data"
MODEL = "Model and density control"
INIT = "Starting points"
APPEARANCE = "Appearance"
OUTPUT = "Checkpoints and logs"
RUN = "Run"
GROUPS = (SCHEDULE, DATA, MODEL, INIT, APPEARANCE, OUTPUT, RUN)


@dataclass(frozen=True)
class Spec:
    """What one field's option is."""

    help: str
    group: str | None = None  # the `--help` heading; None: not on the command line (API and stored configs only)
    short: str | None = None  # a one-letter alias on the command line ("-n")
    name: str | None = None  # the option's name, where it is not the field's (a section's own switch)
    shared: bool = False  # a field every alternative section has: set in the chosen one (module docstring)
    at_least: float | None = None
    more_than: float | None = None
    at_most: float | None = None
    less_than: float | None = None
    choices: tuple[str, ...] | None = None
    parse: Callable[[str], Any] | None = None  # text (the command line's) -> value; ValueError names what is allowed
    steps: str | None = None  # a count of optimiser steps: "schedule" (the run's shape) or "cadence" (logs, checkpoints)
    metavar: str | None = None


@dataclass(frozen=True)
class Section:
    help: str
    prefix: str = ""
    when: tuple[str, str] | None = None  # (choice field, value): the section applies only then


def opt(default: Any, help: str, **spec: Any) -> Any:
    """A config field whose option is `Spec(help, **spec)`."""
    return field(default=default, metadata={"spec": Spec(help, **spec)})


def section(factory: Callable[[], Any], help: str, **kw: Any) -> Any:
    """A nested config field (its fields are options too)."""
    return field(default_factory=factory, metadata={"section": Section(help, **kw)})


def override(base: type, name: str, default: Any) -> Any:
    """`base`'s field `name` with another default (the option is the same one)."""
    return field(default=default, metadata={f.name: f for f in fields(base)}[name].metadata)


@dataclass(frozen=True)
class Option:
    name: str  # cli/train_config.py make_config's keyword; on the command line `--` + name with dashes
    path: tuple[str, ...]  # attribute path from the root config
    types: tuple[type, ...]  # what a value may be (None included when optional)
    default: Any
    spec: Spec
    when: tuple[str, str] | None = None

    @property
    def flag(self) -> str:
        return "--" + self.name.replace("_", "-")

    @property
    def on_cli(self) -> bool:
        return self.spec.group is not None

    @property
    def label(self) -> str:
        """How messages name it: as the user typed it, or by its config name."""
        return self.flag if self.on_cli else self.name

    @property
    def optional(self) -> bool:
        return type(None) in self.types


def _types(annotation: Any) -> tuple[type, ...]:
    if isinstance(annotation, types.UnionType) or typing.get_origin(annotation) is typing.Union:
        return tuple(a for a in typing.get_args(annotation))
    return (annotation,)


@functools.cache
def table(root: type) -> dict[str, tuple[Option, ...]]:
    """Every option of the config tree `root`, by name (a shared name has one Option per
    alternative section)."""
    out: dict[str, list[Option]] = {}

    def walk(cls: type, path: tuple[str, ...], prefix: str, when: tuple[str, str] | None) -> None:
        hints = typing.get_type_hints(cls)
        for f in fields(cls):
            if "section" in f.metadata:
                s: Section = f.metadata["section"]
                walk(type(f.default_factory()), path + (f.name,), s.prefix, s.when or when)  # type: ignore[misc]
                continue
            spec: Spec | None = f.metadata.get("spec")
            if spec is None:
                continue
            name = spec.name or (f.name if spec.shared else prefix + f.name)
            default = f.default if f.default is not dataclasses.MISSING else None
            out.setdefault(name, []).append(Option(name, path + (f.name,), _types(hints[f.name]), default, spec, when))

    walk(root if isinstance(root, type) else type(root), (), "", None)
    for name, alts in out.items():
        if len(alts) > 1 and not all(a.spec.shared and a.when for a in alts):
            raise TypeError(f"option {name!r} is declared twice in {root.__name__}")  # a bug in the config tree
    return {k: tuple(v) for k, v in out.items()}


def _get(obj: Any, path: tuple[str, ...]) -> Any:
    for p in path:
        obj = getattr(obj, p)
    return obj


def applies(cfg: Any, o: Option) -> bool:
    return o.when is None or getattr(cfg, o.when[0]) == o.when[1]


def resolve(cfg: Any, name: str) -> Option | None:
    """The option `name` sets in `cfg` (None: it belongs to an alternative not chosen)."""
    for o in table(type(cfg))[name]:
        if applies(cfg, o):
            return o
    return None


def value(cfg: Any, name: str) -> Any:
    o = resolve(cfg, name)
    if o is None:
        raise KeyError(name)
    return _get(cfg, o.path)


def _not_applicable(cfg: Any, name: str) -> SplatError:
    alts = table(type(cfg))[name]
    choice = alts[0].when[0]  # type: ignore[index]
    o = alts[0]
    return SplatError(f"{o.label} does not apply to --{choice} {getattr(cfg, choice)}: it is an option of "
                      f"--{choice} {' or '.join(a.when[1] for a in alts)}",  # type: ignore[index]
                      hint=f"drop {o.label}, or choose --{choice} {alts[0].when[1]}")  # type: ignore[index]


def apply(cfg: Any, options: dict[str, Any], *, strict: bool = True) -> Any:
    """`cfg` with named options set (choices first, so that what depends on them goes to
    the section chosen). Text for an option with a parser is parsed. An option of an
    alternative not chosen is an error when `strict`, else left out (a preset's)."""
    tab = table(type(cfg))
    unknown = [k for k in options if k not in tab]
    if unknown:
        raise KeyError(f"unknown option(s): {', '.join(unknown)}")  # a bug in the caller
    choosers = {o.when[0] for alts in tab.values() for o in alts if o.when}
    for group in (sorted(k for k in options if k in choosers), [k for k in options if k not in choosers]):
        edits: dict[tuple[str, ...], Any] = {}
        for name in group:
            o = resolve(cfg, name)
            if o is None:
                if strict:
                    raise _not_applicable(cfg, name)
                continue
            v = options[name]
            if isinstance(v, str) and o.spec.parse is not None:
                try:
                    v = o.spec.parse(v)
                except ValueError as exc:
                    raise SplatError(f"{o.label} {v!r}: {exc}") from None
            edits[o.path] = v
        cfg = _set(cfg, edits)
    return cfg


@dataclass(frozen=True)
class Given:
    """Options given by name (the command line's), parsed once: `values` by name, and `typed`,
    the root config's defaults with them applied and checked, where they are read by field."""

    values: dict[str, Any]
    typed: Any

    def over(self, cfg: Any, leave: tuple[str, ...] = ()) -> Any:
        """`cfg` with the options given set, but those named in `leave`."""
        return apply(cfg, {k: v for k, v in self.values.items() if k not in leave})

    def __contains__(self, name: str) -> bool:
        return name in self.values


def parse(root: type, given: dict[str, Any]) -> Given:
    """The options `given` that are not None, text parsed as on the command line, set on `root()`'s
    defaults and checked there (types, ranges, alternatives chosen: one-line SplatError)."""
    typed = apply(root(), {k: v for k, v in given.items() if v is not None})
    check(typed)
    return Given({k: value(typed, k) for k, v in given.items() if v is not None}, typed)


def _set(obj: Any, edits: dict[tuple[str, ...], Any]) -> Any:
    top = {p[0]: v for p, v in edits.items() if len(p) == 1}
    nested: dict[str, dict[tuple[str, ...], Any]] = {}
    for p, v in edits.items():
        if len(p) > 1:
            nested.setdefault(p[0], {})[p[1:]] = v
    for k, sub in nested.items():
        top[k] = _set(getattr(obj, k), sub)
    return replace(obj, **top) if top else obj


def steps_options(root: type, kind: str | None = None) -> tuple[str, ...]:
    """The options counted in optimiser steps (of one kind: "schedule" or "cadence"); the
    typed code that scales them (TrainConfig.for_world, the time plan's Schedule) is held to
    this list by tests/test_options.py."""
    return tuple(n for n, alts in table(root).items() if alts[0].spec.steps and kind in (None, alts[0].spec.steps))


# ---- checking -------------------------------------------------------------------


def _type_name(o: Option) -> str:
    return " | ".join("None" if t is type(None) else t.__name__ for t in o.types)


def type_ok(o: Option, v: Any) -> bool:
    if v is None:
        return o.optional
    if isinstance(v, bool):
        return bool in o.types
    if isinstance(v, int):
        return int in o.types or float in o.types
    if isinstance(v, float):
        return float in o.types
    return any(t not in (type(None), bool, int, float) and isinstance(v, t) for t in o.types)


def _number(v: float) -> str:
    return f"{v:g}" if isinstance(v, float) else str(v)


def range_error(o: Option, v: Any) -> str | None:
    """Why `v` is out of `o`'s range (None: it is not)."""
    s = o.spec
    if v is None or isinstance(v, bool):
        return None
    if isinstance(v, str):
        if s.choices and v not in s.choices:
            return f"{o.label} {v!r} is not known; choose one of {', '.join(s.choices)}"
        return None
    if isinstance(v, float) and not math.isfinite(v):
        return f"{o.label} {v}: must be a finite number"
    lo, hi = (s.at_least, "["), (s.more_than, "(")
    low = lo if lo[0] is not None else hi
    top = (s.at_most, "]") if s.at_most is not None else (s.less_than, ")")
    ok = ((s.at_least is None or v >= s.at_least) and (s.more_than is None or v > s.more_than)
          and (s.at_most is None or v <= s.at_most) and (s.less_than is None or v < s.less_than))
    if ok:
        return None
    if low[0] is not None and top[0] is not None:
        return f"{o.label} {v}: must be in {low[1]}{_number(low[0])}, {_number(top[0])}{top[1]}"
    if s.at_least is not None:
        whole = "a whole number of " if int in o.types and float not in o.types else ""
        return f"{o.label} {v}: must be {'0 or more' if s.at_least == 0 else f'{whole}at least {_number(s.at_least)}'}"
    if s.more_than is not None:
        return f"{o.label} {v}: must be {'positive' if s.more_than == 0 else f'more than {_number(s.more_than)}'}"
    if s.at_most is not None:
        return f"{o.label} {v}: must be at most {_number(s.at_most)}"
    return f"{o.label} {v}: must be less than {_number(s.less_than)}"  # type: ignore[arg-type]


def check(cfg: Any) -> None:
    """Every option that applies to `cfg`: of its type and in its range (one-line SplatError)."""
    for alts in table(type(cfg)).values():
        for o in alts:
            if not applies(cfg, o):
                continue
            v = _get(cfg, o.path)
            if not type_ok(o, v):
                raise SplatError(f"{o.label} is {_shown(v)}, expected {_type_name(o)}")
            if isinstance(v, str) and o.spec.parse is not None:
                try:
                    parsed = o.spec.parse(v)
                except ValueError as exc:
                    raise SplatError(f"{o.label} {v!r}: {exc}") from None
                if parsed != v:
                    raise SplatError(f"{o.label} {v!r}: expected {parsed!r}")
            why = range_error(o, v)
            if why:
                raise SplatError(why)


def _shown(v: Any) -> str:
    return " ".join(repr(v).split())[:40]


def load(root: type, d: dict[str, Any], where: str) -> Any:
    """A stored config (the nested form `dataclasses.asdict` writes) back: unknown keys are
    ignored, missing ones take the defaults, and a value of the wrong type is a one-line
    SplatError naming `where` and the key."""

    def build(cls: type, d: dict[str, Any], path: str) -> Any:
        hints = typing.get_type_hints(cls)
        kw: dict[str, Any] = {}
        for f in fields(cls):
            if f.name not in d:
                continue
            v = d[f.name]
            if "section" in f.metadata:
                if isinstance(v, dict):
                    kw[f.name] = build(type(f.default_factory()), v, f"{path}{f.name}.")  # type: ignore[misc]
                continue
            o = Option(f.name, (f.name,), _types(hints[f.name]), None, Spec(""))
            if not type_ok(o, v) or (isinstance(v, float) and not math.isfinite(v)):
                raise SplatError(f"{where}: {path}{f.name} is {_shown(v)}, expected {_type_name(o)}")
            kw[f.name] = v
        return cls(**kw)

    return build(root, d, "")
