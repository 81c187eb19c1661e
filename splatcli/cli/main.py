"""The `splatcli` entry point: the Typer app and the exit-code policy.

Exit codes: 0 success; 2 bad input or usage (one line `error: ...` on stderr,
no traceback unless --debug); 130 interrupted; 1 internal error. With --json a
failure also prints one object on stdout: {"error": ..., "exit_code": ..., "hint": ...}.
"""

from __future__ import annotations

import os

# Before torch loads its OpenMP runtime: one CPU thread unless OMP_NUM_THREADS says
# otherwise. A second thread is a little faster alone on the machine and many times slower
# when jobs share the cores (docs/guide.md, "Threads"): one is never far from the best.
os.environ.setdefault("OMP_NUM_THREADS", "1")
import json
import sys
import traceback
from typing import Any

import typer
from typer.core import TyperGroup

try:  # recent typer vendors click as typer._click; older ones depend on click
    from typer._click import exceptions as _cx
except ImportError:  # pragma: no cover
    from click import exceptions as _cx  # type: ignore[no-redef]

from .. import __version__
from ..device import tune_allocator
from ..errors import Interrupted, SplatError
from ..train.launch import ERRORS_ENV

tune_allocator()  # every command, and the processes `train --nproc` starts (they run this module)


def _one_line(msg: str) -> str:
    return " ".join(str(msg).split())


def _failure(exc: BaseException, debug: bool) -> tuple[str | None, int, str | None]:
    """What a command raised as (the one line for stderr and the --json object, or None; the exit
    code; a hint). Called in the `except` clause, so that --debug prints the traceback."""
    if isinstance(exc, typer.Exit):  # --help, --version, typer.Exit
        return None, exc.exit_code, None
    if isinstance(exc, typer.Abort):
        return "interrupted", 130, None
    if isinstance(exc, _cx.UsageError):
        hint = f"see `{exc.ctx.command_path} --help`" if exc.ctx is not None else None
        return _one_line(exc.format_message()) + (f" ({hint})" if hint else ""), 2, hint
    if isinstance(exc, _cx.ClickException):
        return _one_line(exc.format_message()), 2, None
    if isinstance(exc, SplatError):
        if debug:
            traceback.print_exc()
        return _one_line(str(exc)), exc.exit_code, exc.hint
    if isinstance(exc, (KeyboardInterrupt, Interrupted)):
        return (_one_line(str(exc)) if isinstance(exc, Interrupted) and str(exc) else "interrupted"), 130, None
    if debug:  # a bug: keep the message, hide the traceback unless asked
        traceback.print_exc()
    hint = "rerun with --debug for the traceback"
    return f"internal error: {type(exc).__name__}: {_one_line(str(exc))} ({hint})", 1, hint


class _Group(TyperGroup):
    """Runs commands with our exit-code policy, both from the console script and
    from typer's CliRunner (which calls `main` too)."""

    def main(self, args: Any = None, prog_name: Any = None, complete_var: Any = None,
             standalone_mode: bool = True, **extra: Any) -> Any:
        argv = list(sys.argv[1:] if args is None else args)
        debug = "--debug" in argv or os.environ.get("SPLATCLI_DEBUG") == "1"
        try:
            rv = super().main(args=argv, prog_name=prog_name or "splatcli", complete_var=complete_var,
                              standalone_mode=False, **extra)
        except _cx.UsageError as exc:
            if type(exc).__name__ == "NoArgsIsHelpError":  # bare `splatcli` or `splatcli CMD`: show help
                sys.stdout.write(exc.format_message() + "\n")
                code = 0 if exc.ctx is None or exc.ctx.parent is None else 2
                sys.stdout.flush()
                if standalone_mode:
                    sys.exit(code)
                return code
            error, code, hint = _failure(exc, debug)
        except (typer.Exit, typer.Abort, KeyboardInterrupt, Exception) as exc:
            error, code, hint = _failure(exc, debug)
        else:
            # Not standalone, typer reports Ctrl-C by returning 130 instead of raising.
            code = rv if isinstance(rv, int) and not isinstance(rv, bool) else 0
            error, hint = ("interrupted" if code == 130 else None), None
        to = os.environ.get(ERRORS_ENV)
        if error is not None and to:  # a worker of `train --nproc`: the launcher reports (train/launch.py)
            with open(os.path.join(to, f"rank{os.environ.get('RANK', '0')}.json"), "w") as f:
                json.dump({"error": error, "exit_code": code, "hint": hint}, f)
        elif error is not None:
            sys.stderr.write(f"error: {error}\n")
            if "--json" in argv:  # scripts tell "bad input" (2) from "crash" (1) without reading English
                sys.stdout.write(json.dumps({"error": error, "exit_code": code, "hint": hint}) + "\n")
        sys.stderr.flush()
        sys.stdout.flush()
        if to and standalone_mode:
            # A launched worker ends here without the interpreter's shutdown, where a
            # thread of torch's process group that still holds a tensor aborts the
            # process (and the launcher then stops the healthy ranks). Its files are
            # closed and its output flushed.
            os._exit(code)
        if standalone_mode:
            sys.exit(code)
        return code


app = typer.Typer(
    cls=_Group,
    name="splatcli",
    help="Photographs to 3D Gaussian splats: process -> train -> render / export / eval, over one project directory.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    context_settings={"help_option_names": ["-h", "--help"]},
)


def _version(value: bool) -> None:
    if value:
        typer.echo(f"splatcli {__version__}")
        raise typer.Exit(0)


@app.callback()
def _root(
    version: bool = typer.Option(False, "--version", callback=_version, is_eager=True, help="Print the version and exit."),
) -> None:
    """Photographs to 3D Gaussian splats.

    A project directory holds everything: `splatcli process CAPTURE -o PROJ`, then
    `splatcli train PROJ`, then `render`, `export` and `eval` on the same PROJ.
    """


from . import eval_cmd, export_cmd, process_cmd, render_cmd, train_cmd, view_cmd  # noqa: E402

app.command("process")(process_cmd.process)
app.command("train")(train_cmd.train)
app.command("render")(render_cmd.render)
app.command("export")(export_cmd.export)
app.command("eval")(eval_cmd.evaluate)
app.command("view")(view_cmd.view)


def main() -> None:
    app()


if __name__ == "__main__":
    main()
