"""An analysis's findings in a few lines for the panel, read from its analysis.json (the
library's summary, :class:`mdlshapemodel.analyze.AnalysisFolder`); analysis.html has the rest."""

from __future__ import annotations


def _number(value: float) -> str:
    return f"{value:.3g}"


def analysisText(summary: dict) -> str:
    """The findings of ``summary`` (analysis.json): the significant points and the global test,
    TFCE's significant points when it ran, each signed map's effect sizes (partial eta^2, and
    the largest Cohen's d of a two-level comparison), and the group classifier's AUC with its
    interval, balanced accuracy and permutation p."""
    significant, global_test = summary["significant_points"], summary["global_test"]
    lines = [f"significant points: {significant['fwer']} of {significant['of']} (FWER), "
             f"{significant['fdr']} (FDR); global test p = {_number(global_test['p'])}"]
    tfce = summary["point_test"]["tfce"]
    if tfce is not None:
        lines.append(f"TFCE: {tfce['significant_points']} significant points (FWER)")
    for effect in summary["effect_sizes"]["maps"]:
        eta = effect["partial_eta2"]
        line = (f"effect size {effect['name']}: partial eta² median {_number(eta['median'])}, "
                f"largest {_number(eta['largest'])}")
        if effect["cohens_d"] is not None:
            d = effect["cohens_d"]
            line += f"; Cohen's d largest {_number(d['value'])} at point {d['at_point']}"
        lines.append(line)
    found = summary.get("classification")
    if found is not None:
        low, high = found["auc_interval"]
        line = (f"classification ({' vs '.join(map(str, found['levels']))}): AUC "
                f"{_number(found['auc'])} (95% interval {_number(low)} to {_number(high)}), "
                f"balanced accuracy {_number(found['balanced_accuracy'])}")
        if found["p"] is not None:
            line += f", p = {_number(found['p'])} ({found['permutations']} permutations)"
        lines.append(line)
    return "\n".join(lines)
