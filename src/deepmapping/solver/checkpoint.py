"""Checkpoints: everything needed to continue an interrupted run with --resume."""

from __future__ import annotations

import os
from pathlib import Path

import torch

HISTORY_KEYS = ("iteration", "epoch", "time_s", "loss", "bce", "chamfer", "ate")


def save(path, trainer) -> None:
    """Write atomically (temp file + rename) so an interrupted save never leaves a broken file."""
    path = Path(path)
    st = trainer.state
    data = {
        "model": trainer.model.state_dict(),
        "direct": trainer.model.direct_poses is not None,
        "optimizer": trainer.opt.state_dict(),
        "generator": trainer.gen.get_state(),
        "epoch": st.epoch,
        "step": st.step,
        "elapsed_s": st.elapsed_s,
        "placed": st.placed,
        "curriculum_steps": st.curriculum_steps,
        "history": st.history,
        "config": trainer.cfg.model_dump(),
        **trainer.extra,
    }
    tmp = path.with_name(path.name + ".tmp")
    torch.save(data, tmp)
    os.replace(tmp, path)


def load(path) -> dict:
    return torch.load(path, map_location="cpu", weights_only=False)


def restore(trainer, data: dict) -> None:
    model = trainer.model
    if data["direct"] and model.direct_poses is None:
        model.make_direct()
        trainer.opt = torch.optim.Adam(model.param_groups(), lr=trainer.cfg.optim.lr)
    model.load_state_dict(data["model"])
    trainer.opt.load_state_dict(data["optimizer"])
    trainer.gen.set_state(data["generator"])
    st = trainer.state
    st.epoch, st.step, st.elapsed_s, st.history = data["epoch"], data["step"], data["elapsed_s"], data["history"]
    st.placed, st.curriculum_steps = data.get("placed", 0), data.get("curriculum_steps", 0)
