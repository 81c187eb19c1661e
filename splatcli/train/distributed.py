"""Data-parallel training over views: what one rank exchanges with the others.

Every rank holds the whole model and renders its own view each step (the view
stream is the one-process stream dealt out in turn, so K ranks see in one step
the K views one process sees in K steps). `Comm.reduce_step` all-reduces the
gradients with the loss and the stop flag in one buffer, so every rank applies
the same update and holds identical parameters and Adam moments. Ranks on one machine
exchange the gradients through shared memory (`_Slots`: each writes its own, one small
collective says all are written, each sums them all in rank order), which costs a few
times less than gloo's all-reduce over loopback sockets. Densification
accumulators stay per rank until a strategy decides (`Comm.combine_rows`), and
are folded into rank 0's before a checkpoint (`Comm.fold_rows`), so a checkpoint
never depends on the number of ranks.

`join(device)` reads the environment torchrun (or `splatcli train --nproc`, which
runs torch's elastic launcher in `launch.py`) gives each worker; without it the
run is a single process and every method is free.
"""

from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Iterable
from dataclasses import dataclass
from datetime import timedelta

import torch
from torch import Tensor, nn

from ..errors import SplatError
from ..sfm import colmap

# A collective that waits longer than this means a peer is stuck (a dead one is noticed
# at once: its sockets close). Evaluation and checkpoints fit easily inside it.
TIMEOUT_S = float(os.environ.get("SPLATCLI_DIST_TIMEOUT", "600"))


SHM_DIR = "/dev/shm"  # where the ranks of one machine share their gradients (absent: gloo's all-reduce)
SHM_HEADROOM = 2  # the buffers take at most half of what is free there (containers often get 64 MB)


class _Slots:
    """Two buffers per rank in shared memory (files under SHM_DIR, unlinked once every rank has
    mapped them), used in turn: a rank writes step k+2's gradients into the buffer it wrote at
    step k only after passing step k+1's collective, so every other rank has read step k's.
    Grown by a quarter beyond the need when the model outgrows them (every rank at the same step,
    since the ranks hold the same model)."""

    def __init__(self, rank: int, world: int):
        self.rank, self.world = rank, world
        self.cap, self.turn = 0, 0
        self.bufs: list[list[Tensor]] = []  # [turn][rank] -> [cap] float32
        self.total = torch.empty(0)  # [cap] this rank's sum of all ranks' gradients
        self.tag = "-".join(os.environ.get(k, "") for k in ("MASTER_PORT", "TORCHELASTIC_RUN_ID"))  # one run's

    def _path(self, rank: int, turn: int) -> str:
        return os.path.join(SHM_DIR, f"splatcli-{self.tag}-{self.cap}-{rank}-{turn}")

    def reserve(self, n: int) -> bool:
        """Buffers for n values on every rank; False (on every rank alike) when the shared memory
        has no room for them: a full tmpfs would kill a process that writes to it (SIGBUS)."""
        if n <= self.cap:
            return True
        cap = n + n // 4 + 1024
        if not _agree(_shm_free() >= SHM_HEADROOM * 2 * self.world * 4 * cap):
            return False
        self.cap = cap
        mine = [self._path(self.rank, t) for t in (0, 1)]
        try:
            own = [torch.from_file(f, shared=True, size=self.cap, dtype=torch.float32) for f in mine]
            _agree(True)  # every rank has made its files
            self.bufs = [[own[t] if r == self.rank else
                          torch.from_file(self._path(r, t), shared=True, size=self.cap, dtype=torch.float32)
                          for r in range(self.world)] for t in (0, 1)]
            _agree(True)  # every rank has mapped every file: the names can go (the mappings stay)
        finally:
            for f in mine:
                with contextlib.suppress(OSError):
                    os.unlink(f)
        self.total = torch.empty(self.cap)
        return True

    def sum(self, parts: list[Tensor], scale: float = 1.0) -> Tensor | None:  # parts: 1-D float32 -> [n]
        """The sum over ranks of the parts times `scale` (each rank writes its parts scaled), or None
        (on every rank) when the shared memory has no room."""
        n = sum(int(p.numel()) for p in parts)
        if not self.reserve(n):
            return None
        bufs, self.turn = self.bufs[self.turn], 1 - self.turn
        o = 0
        for p in parts:  # one pass each, as a copy would be (x 1.0 is one)
            torch.mul(p, scale, out=bufs[self.rank][o:o + p.numel()])
            o += p.numel()
        _agree(True)  # every rank's gradients are written
        out = torch.add(bufs[0][:n], bufs[1][:n], out=self.total[:n])  # the same order on every rank: the same bits
        for b in bufs[2:]:
            out += b[:n]
        return out


def _agree(ok: bool) -> bool:
    """Whether every rank's `ok` holds; every rank has arrived (a one-value all-reduce: gloo's
    barrier costs more)."""
    import torch.distributed as dist

    t = torch.tensor([float(ok)])
    dist.all_reduce(t, op=dist.ReduceOp.MIN)
    return bool(t[0] > 0)


def _shm_free() -> int:
    """Bytes free in SHM_DIR."""
    st = os.statvfs(SHM_DIR)
    return st.f_bavail * st.f_frsize


@dataclass
class Comm:
    """One rank's view of the process group (a single process: rank 0 of 1)."""

    rank: int = 0
    world: int = 1
    local_world: int = 1  # ranks on this machine (they share its memory)
    seconds: float = 0.0  # spent in collectives (communication, and waiting for slower ranks)
    calls: int = 0
    checks: int = 0  # parameter agreement checks passed
    shared: bool = False  # gradients exchanged through shared memory (every rank on this machine)
    _slots: _Slots | None = None

    @property
    def main(self) -> bool:
        """Rank 0 alone writes checkpoints, logs, reports and the manifest."""
        return self.rank == 0

    def _all_reduce(self, t: Tensor, op: str = "sum") -> Tensor:
        import torch.distributed as dist

        t0 = time.perf_counter()
        dist.all_reduce(t, op=dist.ReduceOp.MAX if op == "max" else dist.ReduceOp.SUM)
        self.seconds += time.perf_counter() - t0
        self.calls += 1
        return t

    def reduce_step(self, params: dict[str, nn.Parameter], loss: Tensor, stop: bool) -> tuple[Tensor, bool]:
        """Average every gradient and the loss over the ranks (one all-reduce); the run
        stops when any rank was signalled. A non-finite gradient on any rank makes the
        average non-finite everywhere, so every rank skips the same steps."""
        if self.world == 1:
            return loss.detach(), stop
        ps = list(params.values())
        parts = [(p.grad if p.grad is not None else torch.zeros_like(p)).reshape(-1) for p in ps]
        parts += [loss.detach().reshape(1).to(ps[0].dtype), torch.tensor([float(stop)], device=ps[0].device)]
        flat: Tensor | None = None
        # 1/world folded into each rank's shared-memory write where it is a power of two: exact (but for subnormal
        # gradients, below 1e-38), so the mean has the bits of gloo's sum / world, and the division's pass is saved
        folded = 1.0 / self.world if self.world & (self.world - 1) == 0 else 1.0
        if self.shared and ps[0].device.type == "cpu" and ps[0].dtype == torch.float32:
            if self._slots is None:
                self._slots = _Slots(self.rank, self.world)
            t0 = time.perf_counter()
            flat = self._slots.sum(parts, folded)
            self.seconds += time.perf_counter() - t0
            self.calls += 1
            if flat is None:  # no room in shared memory for this model: gloo from now on
                self.shared, self._slots = False, None
        if flat is None:
            flat, folded = self._all_reduce(torch.cat(parts)), 1.0
        if folded == 1.0:
            flat /= self.world
        o = 0
        for p in ps:
            n = p.numel()
            p.grad = flat[o:o + n].view_as(p)  # views of one buffer: contiguous, as fused Adam needs
            o += n
        return flat[o], bool(flat[o + 1] > 0)

    def combine_rows(self, state: object) -> None:
        """Every rank's accumulated rows of a strategy state merged on every rank, as its
        `REDUCE` says (sum or max). Call before deciding from them."""
        if self.world == 1:
            return
        for name, op in getattr(state, "REDUCE", {}).items():
            self._all_reduce(getattr(state, name), op)

    def fold_rows(self, states: Iterable[object]) -> None:
        """Before a checkpoint: rank 0 holds the merged rows, the others none (so a later
        `combine_rows` counts each view once), whatever the number of ranks that resume."""
        if self.world == 1:
            return
        for st in states:
            self.combine_rows(st)
            if not self.main:
                for name, op in getattr(st, "REDUCE", {}).items():
                    if op == "sum":
                        getattr(st, name).zero_()

    def mean(self, values: Tensor) -> Tensor:  # [M] local sums, last entry a count -> [M - 1] global means
        """Means of per-rank partial sums (evaluation split over the ranks)."""
        if self.world > 1:
            self._all_reduce(values)
        return values[:-1] / values[-1].clamp_min(1)

    def total(self, values: Tensor) -> Tensor:  # [...] -> [...], summed over ranks
        return self._all_reduce(values) if self.world > 1 else values

    def share(self, items: list) -> list:
        """This rank's share of a list (every K-th item)."""
        return items[self.rank::self.world]

    def broadcast_params(self, params: dict[str, nn.Parameter]) -> None:
        """Rank 0's parameters everywhere (the start of a run)."""
        if self.world == 1:
            return
        import torch.distributed as dist

        for p in params.values():
            dist.broadcast(p.data, 0)

    def check_agree(self, params: dict[str, nn.Parameter]) -> None:
        """Bitwise comparison of every rank's parameters with rank 0's (at checkpoints):
        data parallelism is only right while they are identical."""
        if self.world == 1:
            return
        import torch.distributed as dist

        mine = torch.cat([p.detach().reshape(-1) for p in params.values()]).view(torch.int32)
        ref = mine.clone()
        dist.broadcast(ref, 0)
        same = torch.tensor([float(torch.equal(mine, ref))], device=mine.device)
        self._all_reduce(same)
        if int(same) != self.world:
            raise RuntimeError(f"the ranks' parameters differ (rank {self.rank}: "
                               f"{'same as' if torch.equal(mine, ref) else 'differs from'} rank 0)")
        self.checks += 1

    def close(self) -> None:
        if self.world > 1:
            import torch.distributed as dist

            if dist.is_initialized():
                dist.destroy_process_group()


def in_worker() -> bool:
    """Whether this process was started by torchrun / the elastic launcher."""
    return "TORCHELASTIC_RUN_ID" in os.environ or "WORLD_SIZE" in os.environ


def join(device: torch.device) -> Comm:
    """This process's place in a data-parallel run (from torchrun's environment), or a
    single-process Comm. gloo on CPU, NCCL on CUDA."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return Comm()
    # pycolmap's import holds SIGTERM back on the importing thread only: done once gloo's threads run, a SIGTERM
    # from the launcher could reach one of them while glog's handler was in and print its stack trace.
    colmap.load()
    import torch.distributed as dist

    rank = int(os.environ.get("RANK", "0"))
    local_world = int(os.environ.get("LOCAL_WORLD_SIZE", str(world)))
    backend = "nccl" if device.type == "cuda" else "gloo"
    if device.type == "cuda":  # one GPU per rank on each machine
        torch.cuda.set_device(int(os.environ.get("LOCAL_RANK", "0")))
    try:
        dist.init_process_group(backend, timeout=timedelta(seconds=TIMEOUT_S))
    except Exception as exc:  # the rendezvous could not form
        raise SplatError(f"rank {rank} of {world}: could not join the process group "
                         f"({type(exc).__name__}: {' '.join(str(exc).split())[:200]})",
                         hint="check MASTER_ADDR / MASTER_PORT and that every node started") from None
    return Comm(rank=rank, world=world, local_world=local_world,
                shared=device.type == "cpu" and local_world == world and os.access(SHM_DIR, os.W_OK))
