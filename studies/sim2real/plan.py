"""The study's plan: what it trains and on what (``Settings``), one trained model (``Run``),
and every run its tables need (``runs``).

Real2Real trains on the capture (``real``); Sim2Sim and Sim2Real train on a simulated
protocol (``<protocol>_<field>``, ``PROTOCOLS`` by light field, ``FIELDS``), each with
the trainings of ``augment.TRAININGS``, for each task (``TASKS``) from each input
(``INPUTS``), once per seed.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

from phong_reference.bake import METHODS

from . import augment
from .learn import Training

#: The light fields whose replays pick the best one, the published plane field first.
FIELDS = ("plane",) + tuple(m for m in METHODS if m != "plane")
PROTOCOLS = ("base", "extended")
INPUTS = ("full", "patch")
TASKS = ("classification", "localisation")


@dataclass(frozen=True)
class Settings:
    """What the study trains, and on what.

    model : ``learn.MODELS``; seeds : splits and initialisations per run; factor : the
    arrays' block size (4: 160x120 of a 640x480 camera); full_block : the full-image input
    averaged again by this (2: 80x60); patch_px : the patch's side at the arrays'
    resolution (32: 128 full-resolution pixels, about 11 mm of the GelTip's membrane);
    extended_taps : a seeded subset of the extended protocol's taps (None: all 23,040);
    trainings : which of ``augment.TRAININGS`` the simulated sets are trained with;
    inputs, tasks : which of ``INPUTS`` and ``TASKS`` are run (a subset: a costly model on
    the cells that matter); difference : the networks see each image's difference from
    its set's no-contact frame, as shown with the same effects, over its RMS in the image
    circle (``features.difference``), instead of the image as published.
    """

    model: str = "cnn"
    seeds: int = 3
    factor: int = 4
    full_block: int = 2
    patch_px: int = 32
    extended_taps: int | None = None
    trainings: tuple[str, ...] = augment.TRAININGS
    training: Training = field(default_factory=Training)
    workers: int = 2
    inputs: tuple[str, ...] = INPUTS
    tasks: tuple[str, ...] = TASKS
    difference: bool = False

    def to_dict(self) -> dict:
        return {**asdict(self), "training": self.training.to_dict(), "trainings": list(self.trainings),
                "inputs": list(self.inputs), "tasks": list(self.tasks)}

    @property
    def stem(self) -> str:
        """What the outputs are called: ``results.json`` etc. for the default model, else
        ``results-<model>.json``, so a costly model's subset sits beside the default's; with
        difference inputs ``-difference`` follows."""
        return ("" if self.model == "cnn" else f"-{self.model}") + ("-difference" if self.difference else "")


@dataclass(frozen=True)
class Run:
    """One trained model: trained on ``train_set`` (``real`` or ``<protocol>_<field>``)
    with ``training`` (``augment.TRAININGS``), for ``task`` from ``input``, seed ``seed``."""

    train_set: str
    training: str
    input: str
    task: str
    seed: int

    @property
    def name(self) -> str:
        return f"{self.train_set}-{self.training}-{self.input}-{self.task}-{self.seed}"


def runs(settings: Settings, sim_sets: list[str], augmented_sets: list[str]) -> list[Run]:
    """Every run of the study: R2R, each simulated set without effects (S2S and S2R), and
    the plane field's sets with each other training."""
    out = []
    for seed in range(settings.seeds):
        for inp in settings.inputs:
            for task in settings.tasks:
                if task == "localisation" and inp == "patch":
                    continue  # a patch centred on the contact gives its place away
                out.append(Run("real", "none", inp, task, seed))
                out += [Run(s, "none", inp, task, seed) for s in sim_sets]
                out += [Run(s, t, inp, task, seed) for s in augmented_sets for t in settings.trainings if t != "none"]
    return out
