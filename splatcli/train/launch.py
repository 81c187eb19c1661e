"""`splatcli train --nproc K`: K worker processes on this machine through PyTorch's own
elastic launcher (what `torchrun --standalone` runs), each the same `splatcli train`
command with one torch thread (or OMP_NUM_THREADS, which cli/planning.py may choose). They
train the config the launcher built, sent in their environment (cli/planning.py,
`Chosen.env`; cli/train_config.py's `configure` reads it back), not rebuilt from words.

The launcher reports one line: rank 0's own result, or, when a rank died, which rank
and the last checkpoint. SIGINT/SIGTERM reach the workers once (they are in their own
session); they agree on a step, rank 0 checkpoints, and the launcher exits 130.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import socket
import sys
import tempfile
import uuid
from dataclasses import dataclass
from pathlib import Path

import torch

from ..errors import Interrupted, SplatError

# Where a worker of a launched run writes its one-line error instead of the console
# (cli/main.py): the launcher then prints the one that explains the failure.
ERRORS_ENV = "SPLATCLI_ERRORS_TO"


@dataclass
class WorkerError:
    rank: int
    exit_code: int
    message: str | None  # the worker's own one line; None when it died without one
    hint: str | None = None


def free_port(port: int) -> int:
    """`port`, checked free on 127.0.0.1, or any free port when 0."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError as exc:
            raise SplatError(f"--port {port}: cannot listen on 127.0.0.1:{port} ({exc.strerror or exc})",
                             hint="choose another --port, or leave it out to use a free one") from None
        return int(s.getsockname()[1])


def launch(argv: list[str], nproc: int, port: int, project_dir: Path, device: torch.device,
           env: dict[str, str] | None = None) -> None:
    """Run `python -m splatcli <argv>` (a train command of `project_dir`) as `nproc`
    ranks, with `env` added to their environment; return when all succeed. A failure raises one exception with one line:
    Interrupted (exit 130), the workers' own SplatError (exit 2), or RankDied (exit 1)
    naming the rank that died and the last checkpoint."""
    from torch.distributed.elastic.multiprocessing.api import DefaultLogsSpecs, SignalException
    from torch.distributed.elastic.multiprocessing.errors import ChildFailedError
    from torch.distributed.launcher.api import LaunchConfig, elastic_launch

    if nproc < 1:
        raise SplatError(f"--nproc {nproc}: must be at least 1")
    if device.type == "cuda" and nproc > torch.cuda.device_count():
        raise SplatError(f"--nproc {nproc} on {device}: each process needs its own GPU and this machine has "
                         f"{torch.cuda.device_count()}", hint="add --device cpu, or lower --nproc")
    for name in list(logging.root.manager.loggerDict):  # their warnings and tables are not for users
        if name.startswith("torch.distributed"):
            logging.getLogger(name).setLevel(logging.CRITICAL)
    port = free_port(port)
    from ..project import writer_lock

    with writer_lock(project_dir, "train"):  # refuse at once, not after K processes start (rank 0 takes it)
        pass
    with tempfile.TemporaryDirectory(prefix="splatcli-ranks-") as tmp:
        errors = Path(tmp) / "errors"
        errors.mkdir()
        env = {ERRORS_ENV: str(errors), **(env or {})}
        env_before = {k: os.environ.get(k) for k in (*env, "OMP_NUM_THREADS")}
        os.environ.update(env)
        os.environ.setdefault("OMP_NUM_THREADS", "1")
        config = LaunchConfig(
            min_nodes=1, max_nodes=1, nproc_per_node=nproc, run_id=uuid.uuid4().hex,
            rdzv_backend="c10d", rdzv_endpoint=f"127.0.0.1:{port}", rdzv_timeout=120,
            max_restarts=0, monitor_interval=0.2, start_method="spawn",
            logs_specs=DefaultLogsSpecs(log_dir=str(Path(tmp) / "logs")),
        )
        try:
            elastic_launch(config, sys.executable)("-m", "splatcli", *argv)
        except SignalException as exc:
            raise _report(errors, {}, project_dir, signalled=exc.sigval) from None
        except ChildFailedError as exc:
            codes = {int(rank): int(f.exitcode) for rank, f in exc.failures.items()}
            raise _report(errors, codes, project_dir) from None
        except Exception as exc:  # the rendezvous did not form, a port was taken meanwhile, ...
            raise SplatError(f"could not start {nproc} training processes: {type(exc).__name__}: "
                             f"{' '.join(str(exc).split())[:200]}") from None
        finally:
            for k, v in env_before.items():
                if v is None:
                    os.environ.pop(k, None)
                else:
                    os.environ[k] = v


def _read(errors: Path) -> dict[int, WorkerError]:
    out = {}
    for p in errors.glob("rank*.json"):
        try:
            d = json.loads(p.read_text())
            out[int(p.stem[4:])] = WorkerError(int(p.stem[4:]), int(d["exit_code"]), d.get("error"), d.get("hint"))
        except (OSError, ValueError, KeyError):
            continue
    return out


def _latest(project_dir: Path) -> str:
    from ..project import Project

    path = Project(project_dir).latest_checkpoint()
    return f"the last checkpoint is {path}" if path else "no checkpoint was written yet"


def _report(errors: Path, codes: dict[int, int], project_dir: Path,
            signalled: signal.Signals | None = None) -> Exception:
    """The one exception that explains a failed run: a rank that died without a word
    (killed) first, then the lowest rank's own error."""
    said = _read(errors)
    # The launcher stops the other ranks with SIGTERM once one fails: that one explains, and a
    # rank it stopped before that rank's own error was written says nothing (all SIGTERM: from outside).
    failed = {r: c for r, c in codes.items() if c != -signal.SIGTERM} or codes
    for rank, code in sorted(failed.items()):
        if rank not in said:
            how = f"exited with code {code}"
            if code < 0:
                try:
                    how = f"was killed by {signal.Signals(-code).name}"
                except ValueError:
                    how = f"was killed by signal {-code}"
            return RankDied(f"training rank {rank} {how}; the run was stopped; {_latest(project_dir)}",
                            hint=f"continue with `splatcli train {project_dir} --resume`")
    if any(e.exit_code == 130 for e in said.values()) or signalled is not None:
        first = said.get(0) or next(iter(said.values()), None)
        return Interrupted(first.message if first and first.message and first.exit_code == 130
                           else f"interrupted; {_latest(project_dir)}")
    if said:
        e = said[min(said, key=lambda r: (said[r].exit_code != 2, r))]  # a user error explains more than its echo
        err = SplatError(e.message or "training failed")
        err.hint = e.hint
        err.exit_code = e.exit_code
        return err
    return SplatError(f"training failed ({codes})")


class RankDied(SplatError):
    """A training rank died without reporting (killed, crashed hard)."""

    exit_code = 1
