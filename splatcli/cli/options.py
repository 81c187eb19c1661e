"""Typer options generated from a config's fields (options.py): one for each option the
command line shows, under its heading, with its help, and its default as the config and
the presets give it. A command written as

    @config_options(TrainConfig, preset_options())
    def train(project: Path = typer.Argument(...), ..., given: dict[str, Any] = GIVEN) -> None:

gets the options the user gave as `given` (by option name, as cli/train_config.py's
`make_config` takes them, the presets' by name for `--help`);
the config checks their values, so the command line and a stored config are held to the
same ranges with the same messages.
"""

from __future__ import annotations

import functools
import inspect
import typing
from collections.abc import Callable
from typing import Any, Optional

import typer

from .. import options
from ..options import GROUPS, Option

GIVEN: dict[str, Any] = {}  # the placeholder default of a command's `given` parameter


def _shown(v: Any) -> str:
    if v is None:
        return "none"
    if isinstance(v, bool):
        return "on" if v else "off"
    if isinstance(v, float):
        return f"{v:g}"
    return str(v)


def default_text(root: type, alts: tuple[Option, ...], presets: dict[str, dict[str, Any]]) -> str:
    """The default as `--help` shows it: the config's, the other strategies' where they
    differ, and the presets' where they change it."""
    first = alts[0]
    out = _shown(first.default)
    others = [f"--{a.when[0]} {a.when[1]}: {_shown(a.default)}" for a in alts[1:]
              if a.when and a.default != first.default]
    by_preset = [f"{p} {_shown(v[first.name])}" for p, v in presets.items() if first.name in v]
    if others:
        out += "; " + "; ".join(others)
    if by_preset:
        out += "; --preset " + ", ".join(by_preset)
    return out


def _typer_option(root: type, alts: tuple[Option, ...], presets: dict[str, dict[str, Any]]) -> tuple[Any, Any]:
    """(annotation, typer.Option) of one generated option; its default None means "not given"."""
    o = alts[0]
    kinds = [t for t in o.types if t is not type(None)]
    kind = kinds[0] if len(kinds) == 1 else str  # several (sh_degree's int | "auto"): parsed by the config
    decls = [f"{o.flag}/--no-{o.flag[2:]}"] if kind is bool else [o.flag]
    if o.spec.short:
        decls.append(o.spec.short)
    metavar = o.spec.metavar or (f"[{'|'.join(o.spec.choices)}]" if o.spec.choices else None)
    info = typer.Option(None, *decls, help=f"{o.spec.help} (default: {default_text(root, alts, presets)})",
                        rich_help_panel=o.spec.group, metavar=metavar, show_default=False)
    return Optional[kind], info


def config_options(root: type, presets: dict[str, dict[str, Any]] | None = None) -> Callable[[Callable], Callable]:
    """Give a Typer command one option per command-line option of the config `root`."""
    table = options.table(root)
    order = {g: i for i, g in enumerate(GROUPS)}
    names = sorted((n for n, alts in table.items() if alts[0].on_cli), key=lambda n: order[table[n][0].spec.group])

    def wrap(func: Callable) -> Callable:
        hints = typing.get_type_hints(func)
        own = [p.replace(annotation=hints.get(p.name, p.annotation))
               for p in inspect.signature(func).parameters.values() if p.name != "given"]
        generated = []
        for n in names:
            annotation, info = _typer_option(root, table[n], presets or {})
            generated.append(inspect.Parameter(n, inspect.Parameter.KEYWORD_ONLY, default=info, annotation=annotation))
        first_option = next((i for i, p in enumerate(own) if not isinstance(p.default, typer.models.ArgumentInfo)),
                            len(own))
        params = own[:first_option] + generated + [p.replace(kind=inspect.Parameter.KEYWORD_ONLY)
                                                   for p in own[first_option:]]

        @functools.wraps(func)
        def command(**kw: Any) -> Any:
            given = {n: v for n in names if (v := kw.pop(n, None)) is not None}
            return func(**kw, given=given)

        command.__signature__ = inspect.Signature(params)  # type: ignore[attr-defined]
        command.__annotations__ = {p.name: p.annotation for p in params}
        return command

    return wrap

