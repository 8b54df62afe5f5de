"""The benchmark's feature models: the one-sided logistic regression (``fit_features``) and the two-sided one
(``fit_deviations``, the ``state_probe_deviation`` detector), on features given directly."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from seqtrojan.benchmark.detectors import DETECTORS, fit_deviations, fit_features


@dataclass(frozen=True)
class Fake:
    """A suspect reduced to its features (the fitted models read a suspect only through the features function)."""

    features: dict[str, float]


def _read(s: Fake) -> dict[str, float]:
    return s.features


def _split(seed: int = 0) -> tuple[list[Fake], list[int]]:
    """Six clean models with a probe-like feature near 0.25 and six poisoned ones far above (a plain backdoor)."""
    rng = np.random.default_rng(seed)
    clean = [
        Fake({"divergence": float(v), "noise": float(n)}) for v, n in zip(rng.normal(0.25, 0.05, 6), rng.normal(size=6))
    ]
    poisoned = [
        Fake({"divergence": float(v), "noise": float(n)}) for v, n in zip(rng.normal(0.8, 0.05, 6), rng.normal(size=6))
    ]
    return clean + poisoned, [0] * 6 + [1] * 6


def test_a_feature_pushed_below_every_clean_model_is_suspect_on_both_sides_only():
    """Fitted on clean models and plain backdoors, the one-sided model calls a model whose state remembers less than
    any clean one (the probe_camouflage attacker) cleaner than every clean model; the two-sided one ranks it above
    every clean model, and a plain backdoor above it too."""
    suspects, labels = _split()
    one_sided = fit_features(_read, suspects, labels)  # type: ignore[arg-type]
    two_sided = fit_deviations(_read, suspects, labels)  # type: ignore[arg-type]
    clean = [Fake({"divergence": v, "noise": 0.0}) for v in (0.18, 0.25, 0.32)]
    erased = Fake({"divergence": 0.02, "noise": 0.0})
    plain = Fake({"divergence": 0.8, "noise": 0.0})
    assert one_sided.probability(erased) < min(one_sided.probability(c) for c in clean)  # type: ignore[arg-type]
    two = [two_sided.probability(c) for c in clean]  # type: ignore[arg-type]
    assert max(two) < two_sided.probability(erased) < two_sided.probability(plain)  # type: ignore[arg-type]
    assert max(two) < 0.5 < two_sided.probability(plain)  # type: ignore[arg-type]


def test_a_clean_train_model_is_measured_against_the_other_clean_ones():
    """Leave one out: the fit sees each clean train model's deviation from the other clean models (as far as a new
    clean model there would be), not from a mean and spread it helped make; a poisoned model's is from all of them.
    Read from what the fitted scaler saw; a clean model at the edge of the clean range stays under one half."""
    suspects, labels = _split()
    model = fit_deviations(_read, suspects, labels)  # type: ignore[arg-type]
    values = np.array([s.features["divergence"] for s in suspects])
    clean = values[:6]

    def deviation(x: float, others: np.ndarray) -> float:
        return float(np.log1p(((x - others.mean()) / others.std(ddof=1)) ** 2))

    seen = [deviation(v, np.delete(clean, i)) for i, v in enumerate(clean)] + [deviation(v, clean) for v in values[6:]]
    column = model.names.index("divergence")
    assert model.pipeline[0].mean_[column] == pytest.approx(np.mean(seen))
    assert model.transform.mean[column] == pytest.approx(clean.mean())  # type: ignore[union-attr]
    assert model.probability(Fake({"divergence": float(clean.max()), "noise": 0.0})) < 0.5  # type: ignore[arg-type]


def test_too_few_clean_train_models_or_one_label_answer_the_poisoned_share():
    suspects, _ = _split()
    few = suspects[:2] + suspects[6:]
    assert fit_deviations(_read, few, [0, 0] + [1] * 6).probability(few[0]) == pytest.approx(0.75)  # type: ignore[arg-type]
    assert fit_deviations(_read, suspects[:6], [0] * 6).probability(suspects[0]) == 0.0  # type: ignore[arg-type]


def test_the_two_sided_probe_is_registered():
    assert "state_probe_deviation" in DETECTORS.names()
    assert "both sides" in DETECTORS.entry("state_probe_deviation").description


def test_all_features_reads_every_part_s_features_under_its_name_and_learns_from_the_union():
    """``all_features``: the union of its parts' features, each prefixed by its source, in one regression; an
    attacker who flattens one part's signal (here the probe-like one) is still caught by another's (here a
    weight-like one), which the single-part model cannot do."""
    from seqtrojan.benchmark.detectors import AllFeatures

    class TwoParts(AllFeatures):
        def parts(self):
            return {"probe": lambda s: {"divergence": s.features["divergence"]},
                    "weights": lambda s: {"norm": s.features["norm"]}}  # fmt: skip

    def model(divergence: float, norm: float) -> Fake:
        return Fake({"divergence": divergence, "norm": norm})

    rng = np.random.default_rng(1)
    clean = [model(float(d), float(n)) for d, n in zip(rng.normal(0.25, 0.05, 6), rng.normal(1.0, 0.05, 6))]
    plain = [model(float(d), float(n)) for d, n in zip(rng.normal(0.8, 0.05, 6), rng.normal(1.5, 0.05, 6))]
    union = TwoParts()
    assert union.features(model(0.3, 1.2)) == {"probe/divergence": 0.3, "weights/norm": 1.2}
    fitted = union.fit(clean + plain, [0] * 6 + [1] * 6)
    camouflaged = model(0.25, 1.5)  # the probe's reading flattened to the clean level, the weights not
    probe_only = fit_features(lambda s: {"divergence": s.features["divergence"]}, clean + plain, [0] * 6 + [1] * 6)
    assert fitted.probability(camouflaged) > max(fitted.probability(c) for c in clean)
    assert probe_only.probability(camouflaged) < max(probe_only.probability(c) for c in clean)
    assert "all_features" in DETECTORS.names()
