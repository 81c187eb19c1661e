"""Data-parallel training over views: what one rank exchanges with the others.

Every rank holds the whole model and renders its own view each step (the view
stream is the one-process stream dealt out in turn, so K ranks see in one step
the K views one process sees in K steps). `Comm.reduce_step` all-reduces the
gradients with the loss and the stop flag in one buffer, so every rank applies
the same update and holds identical parameters and Adam moments. Densification
accumulators stay per rank until a strategy decides (`Comm.combine_rows`), and
are folded into rank 0's before a checkpoint (`Comm.fold_rows`), so a checkpoint
never depends on the number of ranks.

`join(device)` reads the environment torchrun (or `splatcli train --nproc`, which
runs torch's elastic launcher in `launch.py`) gives each worker; without it the
run is a single process and every method is free.
"""

from __future__ import annotations

import os
import time
from collections.abc import Iterable
from dataclasses import dataclass
from datetime import timedelta

import torch
from torch import Tensor, nn

from ..errors import SplatError

# A collective that waits longer than this means a peer is stuck (a dead one is noticed
# at once: its sockets close). Evaluation and checkpoints fit easily inside it.
TIMEOUT_S = float(os.environ.get("SPLATCLI_DIST_TIMEOUT", "600"))


@dataclass
class Comm:
    """One rank's view of the process group (a single process: rank 0 of 1)."""

    rank: int = 0
    world: int = 1
    local_world: int = 1  # ranks on this machine (they share its memory)
    seconds: float = 0.0  # spent in collectives (communication, and waiting for slower ranks)
    calls: int = 0
    checks: int = 0  # parameter agreement checks passed

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
        flat = torch.cat(parts + [loss.detach().reshape(1).to(ps[0].dtype), torch.tensor([float(stop)], device=ps[0].device)])
        self._all_reduce(flat)
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
    return Comm(rank=rank, world=world, local_world=local_world)
