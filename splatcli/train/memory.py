"""Memory: a plan before training, not a kill during it.

`check_memory` estimates what a run will add to this process (the cached images and
the Gaussians with their gradients, Adam moments and per-step buffers) and compares
it with what this process may still take: the cgroup limit (containers, batch
schedulers), RLIMIT_AS (`ulimit -v`) and the kernel's MemAvailable. A run that cannot
fit stops before loading anything, in one line that names a setting that would fit.
`is_out_of_memory` recognises the allocation errors a run can still meet (the loop
then keeps its last whole step and exits 2 with the same advice).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ..camera import Camera
from ..device import free_memory
from ..errors import SplatError
from ..render.composite import WORK_BYTES  # what a render holds for its backward, at most

# Bytes per Gaussian over a run: parameters (59 floats), their gradients and two Adam
# moments (4 x 236 B), strategy rows, and the per-step projection and compositing
# buffers that grow with the count: a little above what RSS grew by per Gaussian while
# lego and fox densified at the full presets; then the averages of the run's last steps
# (--average: the parameters again and a count, 240 B).
BYTES_PER_GAUSSIAN = 3584 + 240
# A cached training image is uint8 RGB; a coarse-to-fine level adds at most 0.77x.
IMAGE_FACTOR = 1.8
# Without --max-gaussians, densification is assumed to reach this many Gaussians per
# pixel of one training image (above lego's and fox's at the fast preset).
GAUSSIANS_PER_PIXEL = 2.5


@dataclass(frozen=True)
class MemoryPlan:
    need: int  # bytes the run adds
    images: int  # of which the cached images
    gaussians: int  # the Gaussian count assumed
    budgeted: bool  # the count is --max-gaussians (else an estimate)
    free: int | None  # bytes this process may still take (None: unknown)
    limit: str  # what bounds `free`
    longest: int  # the longest image side trained, px
    copies: int = 1  # data-parallel ranks on this machine, each holding images and model


def plan_memory(cameras: list[Camera], init_count: int, max_gaussians: int | None, copies: int = 1) -> MemoryPlan:
    """The bytes a run on these cameras (at the training resolution) adds; `copies`
    data-parallel ranks on this machine each hold the images and the model."""
    pixels = [c.width * c.height for c in cameras]
    images = int(IMAGE_FACTOR * 3 * sum(pixels))
    if max_gaussians is not None:
        n, budgeted = max(int(max_gaussians), init_count), True
    else:
        n, budgeted = max(init_count, int(GAUSSIANS_PER_PIXEL * max(pixels, default=0))), False
    free, limit = free_memory()
    longest = max((max(c.width, c.height) for c in cameras), default=0)
    return MemoryPlan(copies * (images + n * BYTES_PER_GAUSSIAN + WORK_BYTES), copies * images, n, budgeted, free,
                      limit, longest, copies)


# The advice fits this share of what is free: free memory moves while the user reads it (other
# programs, the page cache), and a setting that fills it to the last byte fails on the next try.
ADVISE_SHARE = 0.8


def check_memory(plan: MemoryPlan, max_size: int) -> None:
    """Refuse a run that cannot fit, naming a --max-gaussians or --max-size that would."""
    if plan.free is None or plan.need <= plan.free:
        return
    gb = lambda b: f"{b / 2**30:.1f} GB"  # noqa: E731
    what = f"{plan.gaussians:,} Gaussians" + ("" if plan.budgeted else " (estimated; no --max-gaussians)")
    free = int(plan.free * ADVISE_SHARE)
    room = (free - plan.images) // plan.copies - WORK_BYTES
    if room >= 20_000 * BYTES_PER_GAUSSIAN:
        fix = f"--max-gaussians {room // BYTES_PER_GAUSSIAN // 1000 * 1000}"
    else:  # the images nearly fill it: half of what is free for smaller images, half for the Gaussians
        side = max(16, int(plan.longest * math.sqrt(0.5 * free / max(plan.images, 1))))
        fix = f"--max-size {min(side, max_size)} and --max-gaussians {max(1000, free // 2 // plan.copies // BYTES_PER_GAUSSIAN // 1000 * 1000)}"
    raise SplatError(f"training needs about {gb(plan.need)} ({what} and {gb(plan.images)} of images) but "
                     f"{plan.limit} leaves {gb(plan.free)}; try {fix}")


def is_out_of_memory(exc: BaseException) -> bool:
    """An allocation failure (CPU or CUDA), not another error."""
    if isinstance(exc, (MemoryError, torch.OutOfMemoryError)):
        return True
    msg = str(exc)
    return isinstance(exc, RuntimeError) and ("can't allocate memory" in msg or "out of memory" in msg.lower())
