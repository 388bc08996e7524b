"""One map trained by several processes (``workers`` > 1): torch.distributed data parallelism.

Every worker holds the whole problem (scans, L-Net, M-Net) and takes its part of each batch
(contiguous scans, plus the neighbours its Chamfer pairs need; its own beam and free-space
samples); DistributedDataParallel averages the
gradients, so every worker makes the same optimizer step and the weights stay equal: the same
steps as one process, each spread over the workers. Gloo on CPU, NCCL on CUDA. The decisions that
end or undo a step (the loss's finiteness, the stopping rules, the time budget) are taken on values
reduced over the workers, so all of them take the same branch; the warm start, a resumed
checkpoint and the cold start's placements are worker 0's, broadcast. The cold start's placement
hypotheses are scored (and refined) in shares, the values gathered in order (``split_scores``).

``register`` with ``workers`` = N runs worker 0 in the calling process and starts N - 1 more
(``spawn``); under ``torchrun`` (``WORLD_SIZE`` and ``RANK`` in the environment, any number of
machines) the processes are already there and join the group from the environment. Only worker 0
reports progress and writes checkpoints and results.
"""

from __future__ import annotations

import os
import socket
from contextlib import contextmanager
from datetime import timedelta
from typing import Callable

import numpy as np
import torch
import torch.distributed as dist

from deepmapping.errors import ConfigError, TrainingError
from deepmapping.solver.loss import temporal_pairs

RANK_SEED_STRIDE = 1_000_003  # worker r samples its beams from generator seed + r x this (r = 0: as one process)
TIMEOUT = timedelta(minutes=10)  # a worker that does not reach a collective by then ends the run with an error


def active() -> bool:
    """Whether this process is one of several training one map."""
    return dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1


def world() -> int:
    return dist.get_world_size() if active() else 1


def rank() -> int:
    return dist.get_rank() if active() else 0


def is_main() -> bool:
    return rank() == 0


def local_world() -> int:
    """How many of the workers run on this machine (torchrun's LOCAL_WORLD_SIZE; else all)."""
    return int(os.environ.get("LOCAL_WORLD_SIZE", world()))


def local_device(device: str) -> str:
    """``device`` for this worker: with several workers on CUDA, one GPU each (LOCAL_RANK, or the rank)."""
    if device != "cuda" or not active():
        return device
    if torch.cuda.device_count() < local_world():
        raise ConfigError(f"{local_world()} workers on this machine but {torch.cuda.device_count()} CUDA device(s): "
                          "one GPU each (fewer workers, or --device cpu)")
    index = int(os.environ.get("LOCAL_RANK", rank()))
    torch.cuda.set_device(index)
    return f"cuda:{index}"


def mean(values: torch.Tensor) -> torch.Tensor:
    """The mean of ``values`` over the workers (itself with one)."""
    if not active():
        return values
    out = values.detach().clone()
    dist.all_reduce(out)
    return out / world()


def share(idx: np.ndarray, window: int = 0, samples: np.ndarray | None = None) -> tuple[np.ndarray, int | None, float, float]:
    """This worker's part of a batch of scans ``idx``: (the scans it loads, how many of them, first,
    are its own, the weight of its occupancy loss, the weight of its Chamfer term): ``split`` into
    as many parts as workers, weighted workers x its share, so that the workers' mean (what
    DistributedDataParallel takes of the gradients) is the batch's loss. One process: (idx, None, 1, 1)."""
    if not active():
        return idx, None, 1.0, 1.0
    return split(idx, window, samples, rank(), world(), weight=world())


def split(idx: np.ndarray, window: int, samples: np.ndarray | None, i: int, k: int,
          weight: float = 1.0) -> tuple[np.ndarray, int, float, float]:
    """Part ``i`` of ``k`` of a batch of scans ``idx``: (the scans it loads, how many of them, first,
    are its own, ``weight`` x its share of the occupancy loss, ``weight`` x its share of the Chamfer term).

    Its own scans are a contiguous part of the batch (as equal as can be); after them come the
    batch's scans within ``window`` of one of them, so that each neighbour pair of the batch is
    the Chamfer term's in exactly one part (the one that owns its earlier scan). Shares: of the batch's
    valid samples (``samples``: per scan, all scans; None: equal) and of its pairs (eq. 4 is a mean
    over valid samples, eq. 7 over pairs), so that the parts' terms weighted by them sum to the
    batch's. A part left without scans (a batch smaller than ``k``) loads the batch at share 0."""
    idx = np.asarray(idx)
    own = np.array_split(np.arange(len(idx)), k)[i]
    if len(own) == 0:
        return idx, len(idx), 0.0, 0.0
    pairs = torch.stack(temporal_pairs(torch.as_tensor(idx), window), 1).numpy()
    mine = pairs[np.isin(pairs[:, 0], own)]
    extra = np.setdiff1d(mine[:, 1], own)
    loaded = np.concatenate([own, extra])
    n = np.ones(len(idx)) if samples is None else np.asarray(samples, float)[idx]
    w_bce = weight * n[own].sum() / n.sum() if n.sum() > 0 else weight * len(own) / len(idx)
    w_ch = weight * len(mine) / len(pairs) if len(pairs) else 0.0
    return idx[loaded], len(own), w_bce, w_ch


def part(n: int) -> np.ndarray:
    """This worker's positions of ``n`` items split between the workers (contiguous; all of them with one)."""
    return np.array_split(np.arange(n), world())[rank()]


def split_scores(score: Callable, cands: np.ndarray) -> torch.Tensor:
    """``score(cands)`` (one value per candidate, no gradient) with the candidates split between the
    workers and the values gathered in order (on the CPU); ``score(cands)`` itself with one process."""
    if not active():
        return score(cands)
    mine = part(len(cands))
    values = score(cands[mine]).detach().cpu() if len(mine) else torch.zeros(0)
    parts = [v for v in gather(values) if len(v)]  # worker 0's part is never empty: its dtype, on every worker
    return torch.cat([v.to(parts[0].dtype) for v in parts])


def any_true(flag: bool, device="cpu") -> bool:
    """True on every worker when ``flag`` is True on any."""
    if not active():
        return flag
    t = torch.tensor([1.0 if flag else 0.0], device=device)
    dist.all_reduce(t, op=dist.ReduceOp.MAX)
    return bool(t.item() > 0)


def from_first(obj):
    """Worker 0's ``obj`` on every worker (``obj`` itself with one process)."""
    if not active():
        return obj
    box = [obj]
    dist.broadcast_object_list(box, 0)
    return box[0]


def gather(obj) -> list | None:
    """Every worker's ``obj`` in rank order (on every worker); None with one process."""
    if not active():
        return None
    out: list = [None] * world()
    dist.all_gather_object(out, obj)
    return out


@torch.no_grad()
def broadcast_(*tensors: torch.Tensor | None) -> None:
    """Worker 0's values into every worker's ``tensors`` (in place)."""
    if active():
        for t in tensors:
            if t is not None:
                dist.broadcast(t.data, 0)


def wrap(module: torch.nn.Module, device: torch.device | str, unused: bool = False):
    """``module`` (whose forward returns the loss) in DistributedDataParallel when several workers
    train; ``module`` itself otherwise. Buffers (the scans) are not broadcast: every worker loaded
    them. ``unused``: some parameters get no gradient in these steps (the L-Net during the M-Net
    warm-up)."""
    if not active():
        return module
    import warnings

    from torch.nn.parallel import DistributedDataParallel

    ids = [torch.device(device).index or 0] if torch.device(device).type == "cuda" else None
    with warnings.catch_warnings():  # newer torch renames broadcast_buffers; the old name works from 2.3 on
        warnings.simplefilter("ignore", FutureWarning)
        return DistributedDataParallel(module, device_ids=ids, broadcast_buffers=False, find_unused_parameters=unused)


def backend(device: str) -> str:
    return "nccl" if device == "cuda" else "gloo"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def from_environment() -> bool:
    """Whether a launcher (torchrun) started this process as one of several workers."""
    return int(os.environ.get("WORLD_SIZE", "1")) > 1 and "RANK" in os.environ


@contextmanager
def group(workers: int, device: str, start_others: Callable[[int, str], list] | None = None):
    """A process group for the ``with`` block: from the environment (torchrun), or with this process
    as worker 0 of ``workers`` on this machine, ``start_others(port, addr)`` starting the rest (it
    returns their process handles, joined at the end). Nothing when one worker and no launcher."""
    if active() or (workers <= 1 and not from_environment()):
        yield
        return
    procs: list = []
    finished = False
    try:
        if from_environment():
            dist.init_process_group(backend(device), init_method="env://", timeout=TIMEOUT)
        else:
            addr, port = "127.0.0.1", free_port()
            procs = start_others(port, addr) if start_others else []
            dist.init_process_group(backend(device), init_method=f"tcp://{addr}:{port}", rank=0, world_size=workers,
                                    timeout=TIMEOUT)
        yield
        finished = True
    finally:  # an error or Ctrl-C here ends the started workers too (theirs is the same, or they wait)
        leave()
        for p in procs:
            p.join(timeout=None if finished else 30)
            if p.is_alive():
                p.terminate()
    failed = [p.exitcode for p in procs if p.exitcode]
    if failed:
        raise TrainingError(f"a training worker ended with exit code {failed[0]}")


def join_group(rank_: int, workers: int, port: int, addr: str, device: str) -> None:
    """In a started worker: join worker 0's group."""
    dist.init_process_group(backend(device), init_method=f"tcp://{addr}:{port}", rank=rank_, world_size=workers,
                            timeout=TIMEOUT)


def leave() -> None:
    if dist.is_available() and dist.is_initialized():
        dist.destroy_process_group()
