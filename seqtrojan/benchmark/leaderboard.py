"""Score every registered detector on a zoo's test and holdout splits: ``seqtrojan zoo detect --zoo Z --out S``.

1. The zoo's models are read with their truth (``label.json``) and factors; a model whose folder, card, weights
   or label is malformed is listed as rejected with its reason (one line) and the rest go on. A poisoned model
   whose backdoor does not work (``functional_backdoor`` false: its final attack success below the zoo's
   ``functional_at``) is left out and listed as excluded: a benchmark's poisoned models must be backdoored. So is a
   model of either label that has not learned its task (``learned_task`` false: its clean success below the zoo's
   ``learned_at``): it would be told apart by its failing behaviour, not by a backdoor.
2. The splits (:mod:`seqtrojan.benchmark.splits`) are written to ``S/splits.json``.
3. Each detector of :data:`~seqtrojan.benchmark.detectors.DETECTORS` is fitted on the train split's suspects
   (:mod:`seqtrojan.benchmark.suspect`: networks and clean envs only), once per env (a zoo of several envs: each
   env's models are answered by the fit on that env's train models, as a detector that is told the clean env would
   specialise; an env the train split lacks by the fit on every train model), and asked for every test and holdout
   model's probability, timed per model; its predictions go to ``S/predictions/<detector>.json`` as soon as it is
   done, so a stopped run resumes with the detectors it had not finished (and a changed split scores them again).
   With a per-model time budget (``budget_s``), an answer that took longer counts as no opinion (probability one
   half; ``over_budget`` in its prediction and the count in the detector's result): a Python call cannot be
   stopped from outside without losing the process, so the budget is enforced on the answer, not the clock.
4. ``S/leaderboard.json``: per detector and split, ROC-AUC, cross-entropy, Brier score and mean runtime per model,
   each with a 95% bootstrap interval over models, and the same by factor (env, cell, widths, attack).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from seqtrojan.benchmark.detectors import DETECTORS, FittedDetector
from seqtrojan.benchmark.scoring import BOOTSTRAP_ROUNDS, Scores, score, score_by_factor
from seqtrojan.benchmark.splits import (
    ATTACK_FACTORS,
    SplitConfig,
    ZooEntry,
    assign_splits,
    check_trainable,
    model_factors,
)
from seqtrojan.benchmark.suspect import Suspect, load_suspect
from seqtrojan.defense.results import Rejected
from seqtrojan.errors import ConfigError, SeqTrojanError
from seqtrojan.serde import from_dict, to_dict
from seqtrojan.train.logger import make_progress

if TYPE_CHECKING:
    from rich.progress import Progress

LEADERBOARD_FILE = "leaderboard.json"
SPLITS_FILE = "splits.json"


@dataclass(frozen=True)
class ModelPrediction:
    model_id: str
    split: str
    label: int
    probability: float
    seconds: float
    over_budget: bool = False
    """the answer took longer than the budget and was replaced by one half"""


@dataclass(frozen=True)
class DetectorPredictions:
    """One detector's answers (what ``predictions/<detector>.json`` holds)."""

    detector: str
    splits: dict[str, str]
    """the split assignment they were made under (a resume checks it)"""
    fit_seconds: float
    predictions: tuple[ModelPrediction, ...]
    fits: dict[str, int] = field(default_factory=dict)
    """env -> the train models its fit learned from (:data:`ALL_ENVS`: the fit on every train model, which answers
    the models of an env the train split does not hold); empty in predictions written before fits were per env"""


ALL_ENVS = "*"
"""the key of the fit on every env's train models in :attr:`DetectorPredictions.fits`"""


@dataclass(frozen=True)
class SplitResult:
    split: str
    scores: Scores
    by_factor: dict[str, dict[str, Scores]]


@dataclass(frozen=True)
class DetectorResult:
    detector: str
    description: str
    fit_seconds: float
    splits: tuple[SplitResult, ...]
    over_budget: int = 0
    """answers that took longer than the per-model budget (each scored as one half)"""


@dataclass(frozen=True)
class Leaderboard:
    zoo: str
    models: dict[str, int]
    """models per split"""
    rejected: tuple[Rejected, ...]
    excluded: tuple[Rejected, ...]
    """poisoned models left out because their backdoor does not work"""
    detectors: tuple[DetectorResult, ...]


def zoo_holdout(zoo: Path) -> dict[str, tuple[str, ...]]:
    """The holdout a zoo was built with (``zoo.json``'s ``holdout``; empty for a zoo without one)."""
    from seqtrojan.zoo.build import MAX_ZOO_CONFIG_BYTES, read_json_file

    path = zoo / "zoo.json"
    if not path.is_file():
        return {}
    try:
        spec = read_json_file(path, MAX_ZOO_CONFIG_BYTES)
    except (OSError, ValueError, SeqTrojanError) as err:
        raise SeqTrojanError(f"{str(path)!r} is not a readable zoo config: {err}") from None
    held = spec.get("holdout", {}) if isinstance(spec, dict) else None
    if not isinstance(held, dict) or not all(
        isinstance(k, str) and isinstance(v, list) and all(isinstance(x, str) for x in v) for k, v in held.items()
    ):
        raise SeqTrojanError(f"{str(path)!r}: holdout must map factor names to lists of values")
    return {k: tuple(v) for k, v in held.items()}


def read_zoo(zoo: Path) -> tuple[list[ZooEntry], list[Suspect], list[Rejected], list[Rejected]]:
    """Every usable model of ``zoo/models`` as an entry (truth) and a suspect (what detectors see), the rejected
    ones with their reasons, and those excluded because their backdoor does not work or they have not learned their
    task."""
    from seqtrojan.zoo.build import not_learned_reason, read_label

    folder = zoo / "models"
    if not folder.is_dir():
        raise SeqTrojanError(f"{str(zoo)!r} is not a zoo (no models/ folder)")
    entries, suspects, rejected, excluded = [], [], [], []
    for path in sorted(p for p in folder.iterdir() if p.is_dir()):
        try:
            truth = read_label(path)
            suspect = load_suspect(path)
        except SeqTrojanError as err:
            rejected.append(Rejected(path.name, " ".join(str(err).split())))
            continue
        if truth["label"] == "backdoored" and truth.get("functional_backdoor") is False:
            excluded.append(Rejected(path.name, f"backdoor not functional (attack success {truth['attack_success']})"))
            continue
        not_learned = not_learned_reason(truth)
        if not_learned is not None:
            excluded.append(Rejected(path.name, not_learned))
            continue
        entries.append(ZooEntry(path.name, path, int(truth["label"] == "backdoored"), model_factors(truth)))
        suspects.append(suspect)
    return entries, suspects, rejected, excluded


def run_leaderboard(
    zoo: Path, out: Path, splits: SplitConfig | None = None, detectors: Sequence[str] | None = None,
    rounds: int = BOOTSTRAP_ROUNDS, log: Callable[[str], None] = print, budget_s: float | None = None,
    progress: bool = False,
) -> Leaderboard:  # fmt: skip
    """Fit and score ``detectors`` (default: every registered one) on ``zoo``; see the module docstring.
    ``budget_s``: seconds a detector may take per model (None: no limit). ``progress``: a progress bar per
    detector (fitting, then the test and holdout models it scores)."""
    if budget_s is not None and not budget_s > 0:
        raise ConfigError(f"the per-model budget must be a positive number of seconds, got {budget_s!r}")
    names = list(detectors) if detectors is not None else DETECTORS.names()
    for name in names:
        DETECTORS.get(name)  # an unknown name is refused before anything is read or written
    cfg = splits or SplitConfig()
    entries, suspects, rejected, excluded = read_zoo(zoo)
    for r in rejected:
        log(f"rejected {r.model}: {r.reason}")
    if excluded:
        log(f"excluded {len(excluded)} model(s) whose backdoor does not work or that have not learned their task: "
            f"{', '.join(r.model for r in excluded)}")  # fmt: skip
    assignment = assign_splits(entries, cfg)
    check_trainable(entries, assignment)
    out.mkdir(parents=True, exist_ok=True)
    _write(out / SPLITS_FILE, assignment)
    results = []
    with make_progress(progress) as bar:
        for name in names:
            answers = _predictions(name, entries, suspects, assignment, out, log, bar)
            results.append(_result(name, entries, _within_budget(answers, budget_s), cfg.seed, rounds))
    counts = {split: sum(1 for s in assignment.values() if s == split) for split in ("train", "test", "holdout")}
    board = Leaderboard(str(zoo), counts, tuple(rejected), tuple(excluded), tuple(results))
    _write(out / LEADERBOARD_FILE, to_dict(board))
    return board


def _predictions(
    name: str, entries: Sequence[ZooEntry], suspects: Sequence[Suspect], assignment: dict[str, str], out: Path,
    log: Callable[[str], None], bar: Progress,
) -> DetectorPredictions:  # fmt: skip
    path = out / "predictions" / f"{name}.json"
    if path.is_file():
        try:
            done = from_dict(DetectorPredictions, _read(path), "")
        except (ConfigError, ValueError):
            done = None
        one_env = len({e.factors["env"] for e in entries}) == 1  # fitted alike before and after fits were per env
        if done is not None and done.splits == assignment and done.detector == name and (done.fits or one_env):
            log(f"{name}: predictions found in {path}")
            return done
    train = [(e, s) for e, s in zip(entries, suspects) if assignment[e.model_id] == "train"]
    scored = [(e, s) for e, s in zip(entries, suspects) if assignment[e.model_id] != "train"]
    task = bar.add_task(name, total=len(scored), info=f"fitting on {len(train)} models")
    fits, counts, fit_seconds = _fit_per_env(name, train, {e.factors["env"] for e, _ in scored})
    bar.update(task, info="scoring")
    answers = []
    for entry, suspect in scored:
        split = assignment[entry.model_id]
        fitted = fits[entry.factors["env"]]
        start = time.perf_counter()
        p = float(fitted.probability(suspect))
        seconds = time.perf_counter() - start
        if not 0.0 <= p <= 1.0:
            raise SeqTrojanError(f"detector {name!r} answered {p!r} for {entry.model_id}, not a probability")
        answers.append(ModelPrediction(entry.model_id, split, entry.label, p, seconds))
        bar.advance(task)
    result = DetectorPredictions(name, dict(assignment), fit_seconds, tuple(answers), counts)
    path.parent.mkdir(parents=True, exist_ok=True)
    _write(path, to_dict(result))
    per_env = f" (per env: {', '.join(f'{k} on {n} models' for k, n in counts.items())})" if len(counts) > 1 else ""
    log(f"{name}: fitted in {fit_seconds:.1f} s{per_env}, {len(answers)} models scored")
    return result


def _fit_per_env(
    name: str, train: Sequence[tuple[ZooEntry, Suspect]], envs: set[str]
) -> tuple[dict[str, FittedDetector], dict[str, int], float]:
    """Detector ``name`` fitted once per env of ``envs`` on that env's train models, or for an env the train split
    lacks on every train model (:data:`ALL_ENVS`); each env's fit, each fit's train models and the seconds fitting
    took."""
    by_key: dict[str, FittedDetector] = {}
    counts: dict[str, int] = {}
    seconds = 0.0
    train_envs = {e.factors["env"] for e, _ in train}
    for env in sorted(envs):
        key = env if env in train_envs else ALL_ENVS
        if key not in by_key:
            rows = [(e, s) for e, s in train if key in (ALL_ENVS, e.factors["env"])]
            start = time.perf_counter()
            by_key[key] = DETECTORS.get(name).fit([s for _, s in rows], [e.label for e, _ in rows])
            seconds += time.perf_counter() - start
            counts[key] = len(rows)
    return {env: by_key[env if env in train_envs else ALL_ENVS] for env in envs}, counts, seconds


def _within_budget(answers: DetectorPredictions, budget_s: float | None) -> DetectorPredictions:
    """``answers`` with every answer over ``budget_s`` seconds replaced by one half and marked."""
    if budget_s is None:
        return answers
    kept = tuple(
        dataclasses.replace(a, probability=0.5, over_budget=True) if a.seconds > budget_s else a
        for a in answers.predictions
    )
    return dataclasses.replace(answers, predictions=kept)


def _result(
    name: str, entries: Sequence[ZooEntry], answers: DetectorPredictions, seed: int, rounds: int
) -> DetectorResult:
    factors = {e.model_id: e.factors for e in entries}
    splits = []
    for split in ("test", "holdout"):
        rows = [a for a in answers.predictions if a.split == split]
        if not rows:
            continue
        labels, probs, secs = [a.label for a in rows], [a.probability for a in rows], [a.seconds for a in rows]
        rows_factors = [factors[a.model_id] for a in rows]
        by_factor = score_by_factor(labels, probs, secs, rows_factors, ATTACK_FACTORS, seed, rounds)
        splits.append(SplitResult(split, score(labels, probs, secs, seed, rounds), by_factor))
    over = sum(a.over_budget for a in answers.predictions)
    return DetectorResult(name, DETECTORS.entry(name).description, answers.fit_seconds, tuple(splits), over)


def _write(path: Path, data: object) -> None:
    from seqtrojan.zoo.build import write_json_atomic

    write_json_atomic(path, data)


def _read(path: Path) -> object:
    from seqtrojan.zoo.build import read_json_file

    return read_json_file(path, 256 << 20)
