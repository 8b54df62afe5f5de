"""Defenses: the online state monitor and the mitigations of the backdoored agent, and offline detection from the
weights on a zoo."""

from __future__ import annotations

import html

from seqtrojan.defense.results import DefenseResult, DetectionResult
from seqtrojan.report.markup import ci, rate
from seqtrojan.stats import auc_interval

FEW_MODELS = 20
"""below this many models in a class, the report warns that an AUC from them is a rough estimate"""


def defense_section(defense: DefenseResult | None, detection: DetectionResult | None) -> list[str]:
    parts = ["<h2>Defenses</h2>"]
    if defense:
        parts += _monitor(defense) + _mitigation(defense)
    if detection:
        parts += _detection(detection)
    return parts


def _monitor(defense: DefenseResult) -> list[str]:
    m = defense.monitor
    table = (
        f"<h3>Online state monitor</h3><p class='note'>Calibrated only on the deployed agent's own clean episodes "
        f"(no trigger knowledge); threshold {m.threshold:.2f} (largest |z| over all h and c units) "
        f"for a 1% per-episode false-alarm target; {m.episodes} fresh episodes per row on {m.grid}.</p>"
        "<table><tr><th class='l'>measure</th><th>value [95% CI]</th></tr>"
        f"<tr><td class='l'>false-alarm rate (normal env)</td><td>{rate(m.normal_alarm.false_alarm)}</td></tr>"
        f"<tr><td class='l'>detection rate (trojan env, alarm at or after the trigger)</td>"
        f"<td>{rate(m.trojan_alarm.detected)}</td></tr>"
        f"<tr><td class='l'>alarm before the trigger (trojan env)</td>"
        f"<td>{rate(m.trojan_alarm.alarm_before_trigger)}</td></tr>"
        f"<tr><td class='l'>median steps from trigger to alarm</td>"
        f"<td>{m.trojan_alarm.median_steps_to_detect}</td></tr>"
        f"<tr><td class='l'>attack success without the monitor</td>"
        f"<td>{rate(m.attack_success_undefended)}</td></tr>"
        f"<tr><td class='l'>attack success with alarm-and-reset</td><td>{rate(m.trojan_reset.attack_success)}"
        f"</td></tr><tr><td class='l'>clean success without the monitor</td>"
        f"<td>{rate(m.clean_success_undefended)}</td></tr>"
        f"<tr><td class='l'>clean success with alarm-and-reset</td><td>{rate(m.normal_reset.success)}</td></tr>"
        "</table>"
    )
    return [table, trigger_code_note(defense.trigger_value)]


def _mitigation(defense: DefenseResult) -> list[str]:
    parts = ["<h3>Mitigation</h3><table><tr><th class='l'>model</th><th>clean success</th><th>attack success</th></tr>"]
    for arm in defense.mitigation.values():
        parts.append(
            f"<tr><td class='l'>{html.escape(arm.title)}</td><td>{rate(arm.clean_success)}</td>"
            f"<td>{rate(arm.attack_success)}</td></tr>"
        )
    parts.append("</table>")
    return parts


def _detection(detection: DetectionResult) -> list[str]:
    n_clean, n_backdoored = detection.clean_models, detection.backdoored_models
    parts = [
        "<h3>Offline detection from the weights (zoo)</h3><p class='note'>Standardised logistic regression on "
        "size-invariant statistics of the LSTM parameters; every model scored by a detector trained without it "
        f"(stratified {detection.scores[0].folds}-fold), the way TrojAI scores detectors. "
        f"{n_clean} clean and {n_backdoored} backdoored models; ROC-AUC with a 95% interval (Newcombe's "
        "score interval, which covers which models were drawn, not the refitting across folds).</p>",
        few_models_warning(n_clean, n_backdoored),
        "<table><tr><th class='l'>features</th><th>#</th><th>models</th><th>ROC-AUC [95% CI]</th>"
        "<th>cross-entropy</th><th>Brier</th></tr>",
    ]
    for r in detection.scores:
        parts.append(
            f"<tr><td class='l'>{r.group}</td><td>{r.features}</td><td>{r.models}</td>"
            f"<td>{auc_cell(r.roc_auc, n_backdoored, n_clean)}</td><td>{r.cross_entropy:.3f}</td>"
            f"<td>{r.brier:.3f}</td></tr>"
        )
    parts.append("</table>")
    held = [h for h in detection.held_out if h.roc_auc is not None]
    if held:
        parts.append(
            "<p class='note'>Held out: for each architecture, trigger code or curriculum of the zoo, a detector "
            "trained on the models without it scores the models with it (does it carry over to a kind of model "
            "it never saw?).</p><table><tr><th class='l'>left out, one value at a time</th><th>values</th>"
            "<th>ROC-AUC (all out-of-group predictions)</th><th>cross-entropy</th><th>Brier</th>"
            "<th class='l'>ROC-AUC within each value</th></tr>"
        )
        for h in held:
            within = ", ".join(
                f"{html.escape(str(g.value))}: {g.roc_auc:.2f}" for g in h.groups if g.roc_auc is not None
            )
            parts.append(
                f"<tr><td class='l'>{h.key}</td><td>{len(h.groups)}</td><td>{h.roc_auc:.3f}</td>"
                f"<td>{h.cross_entropy:.3f}</td><td>{h.brier:.3f}</td><td class='l'>{within}</td></tr>"
            )
        parts.append("</table>")
    fb = detection.functional_backdoors
    if fb.functional + fb.not_functional:
        aucs = ", ".join(
            f"{auc_cell(auc, count, n_clean)} for the {name} ones"
            for auc, count, name in ((fb.functional_roc_auc, fb.functional, "working"),
                                     (fb.not_functional_roc_auc, fb.not_functional, "failed")) if auc is not None
        )  # fmt: skip
        aucs = f"ROC-AUC against the clean models: {aucs}" if aucs else ""
        parts.append(
            f"<p class='note'>{fb.functional} backdoored models have a working backdoor (final trojan-env "
            f"success &ge; {fb.functional_at:g}) and {fb.not_functional} do not; all count as backdoored "
            f"above, as their training made them. {aucs}.</p>"
        )
    if detection.auc_by_trigger_value:
        items = ", ".join(f"{k}: {v:.3f}" for k, v in detection.auc_by_trigger_value.items())
        parts.append(
            f"<p class='note'>ROC-AUC against the clean models, by the trigger's cell code: {items} (each from "
            f"the few backdoored models with that code: rough estimates).</p>"
        )
    for bad in detection.rejected:
        parts.append(f"<p class='note'>Rejected {html.escape(bad.model)}: {html.escape(bad.reason)}</p>")
    return parts


def auc_cell(auc: float, positives: int, negatives: int) -> str:
    """An AUC with its 95% interval (see :func:`seqtrojan.stats.auc_interval`)."""
    if positives < 1 or negatives < 1:
        return f"{auc:.3f}"
    return f"{auc:.3f} {ci(auc_interval(auc, positives, negatives))}"


def few_models_warning(n_clean: int, n_backdoored: int) -> str:
    if min(n_clean, n_backdoored) >= FEW_MODELS:
        return ""
    return (
        f"<p class='note'><b>Caution:</b> only {n_clean} clean and {n_backdoored} backdoored models (fewer than "
        f"{FEW_MODELS} in a class): every AUC below is a rough estimate, as its interval shows, and an AUC of 1 from "
        "so few models is weak evidence that the detector works.</p>"
    )


def trigger_code_note(value: str) -> str:
    """Next to the monitor's detection rate: how unusual the defended agent's trigger cell code ``value`` is."""
    if value == "trigger":
        return (
            "<p class='note'>This agent's trigger uses it. The default trigger draws the dedicated cell code "
            "<code>trigger</code>, which never occurs in normal play: at the trigger step the agent reads an input "
            "channel that is never active in the calibration episodes, so detecting that trigger is the easiest case "
            "for the monitor. A trigger drawn with ordinary cells (holes, walls) offers no such never-seen input.</p>"
        )
    return (
        f"<p class='note'>This agent's trigger draws the cell code <code>{html.escape(str(value))}</code>, which "
        "also occurs in normal play, so the monitor sees no out-of-distribution code at the trigger step (unlike "
        "the default trigger, whose dedicated <code>trigger</code> code never occurs in normal play).</p>"
    )
