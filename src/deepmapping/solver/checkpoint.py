"""Checkpoints: everything needed to continue an interrupted run with --resume.

A checkpoint is taken only where the state is consistent: after a whole epoch (or a whole
curriculum stage) and its log. Resuming from it repeats exactly what the uninterrupted run
would have done next (same seed and threads: bit-identical poses), whether the run was stopped
by Ctrl-C or killed (kill -9, power loss). The same in-memory copy is what training rolls back
to when a step goes NaN/inf (``Trainer.guarded``).
"""

from __future__ import annotations

import copy
from pathlib import Path

import torch

from deepmapping.io.atomic import atomic_write
from deepmapping.solver import distributed

HISTORY_KEYS = ("iteration", "epoch", "time_s", "loss", "bce", "chamfer", "ate")


def capture(trainer) -> dict:
    """The trainer's state as a checkpoint dict, copied (training goes on changing the originals).

    The model's constant buffers (the scans) are shared, not copied: they never change.
    """
    st, model = trainer.state, trainer.model
    constant = getattr(model, "constant_buffers", ())
    return {
        "model": {k: v if k in constant else v.detach().clone() for k, v in model.state_dict().items()},
        "direct": model.direct_poses is not None,
        "optimizer": copy.deepcopy(trainer.opt.state_dict()),
        "generator": trainer.gen.get_state(),
        "generators": distributed.gather(trainer.gen.get_state()),  # several workers: each one's, by rank
        "epoch": st.epoch,
        "step": st.step,
        "elapsed_s": st.elapsed_s,
        "placed": st.placed,
        "curriculum_steps": st.curriculum_steps,
        "reviewed": list(st.reviewed),
        "history": copy.deepcopy(st.history),
        "lr_scale": st.lr_scale,
        "rollbacks": copy.deepcopy(st.rollbacks),
        "early_stop_ref": None if st.early_stop_ref is None else st.early_stop_ref.copy(),
        "epoch_losses": list(st.epoch_losses),
        "stop_reason": st.stop_reason,
        "places": None if st.places is None else st.places.copy(),
        "places_epoch": st.places_epoch,
        "config": trainer.cfg.model_dump(),
        **trainer.extra,
    }


def write(path, data: dict) -> None:
    """Write atomically (temp file + rename) so an interrupted save never leaves a broken file;
    a full disk is an ``OutputError`` naming ``path`` and the previous checkpoint stays."""
    atomic_write(Path(path), lambda f: torch.save(data, f))


def load(path) -> dict:
    return torch.load(path, map_location="cpu", weights_only=False)


def restore(trainer, data: dict) -> None:
    """Set the trainer to ``data`` (a checkpoint or ``capture``), which stays unchanged (no aliasing:
    a snapshot can be restored again)."""
    model = trainer.model
    if data["direct"] and model.direct_poses is None:
        model.make_direct()
        trainer.opt = torch.optim.Adam(model.param_groups(), lr=trainer.cfg.optim.lr)
    model.load_state_dict(data["model"])
    # the optimizer adopts the given state tensors as they are: give it copies
    trainer.opt.load_state_dict(copy.deepcopy(data["optimizer"]))
    gens = data.get("generators")
    if gens is not None and len(gens) == distributed.world():
        trainer.gen.set_state(gens[distributed.rank()])
    else:
        trainer.gen.set_state(data["generator"])
    st = trainer.state
    st.epoch, st.step, st.elapsed_s = data["epoch"], data["step"], data["elapsed_s"]
    st.history = copy.deepcopy(data["history"])
    st.placed, st.curriculum_steps = data.get("placed", 0), data.get("curriculum_steps", 0)
    st.reviewed = list(data.get("reviewed", []))
    st.lr_scale, st.rollbacks = data.get("lr_scale", 1.0), copy.deepcopy(data.get("rollbacks", []))
    ref = data.get("early_stop_ref")
    st.early_stop_ref = None if ref is None else ref.copy()
    st.epoch_losses, st.stop_reason = list(data.get("epoch_losses", [])), data.get("stop_reason", "")
    places = data.get("places")
    st.places = None if places is None else places.copy()
    st.places_epoch = data.get("places_epoch", -1)
