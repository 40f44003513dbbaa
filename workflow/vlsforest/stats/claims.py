"""What Weiser et al. (2021) state, and the tolerances their own words and numbers give.

A finding is judged by what the paper claims. Where it claims a direction ("overestimate",
"too high", "lowers"), the mean effect over the trees must lie beyond the metric's negligible
effect in that direction and its 95 % bootstrap interval must exclude zero; where it claims
that something changes "nothing", the whole interval must lie within ± the negligible effect;
where it gives a size ("≈ +8 pp", "≈ 50×"), our value must lie within the stated tolerance of
it. Every tolerance is taken from the paper, never from our numbers, and carries its source.
The paper's numbers quoted here are those of its Results and Table 5 (restated in the project's
reference notes on the study).
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = [
    "Tolerance",
    "HEIGHT_METRICS",
    "NEGLIGIBLE_HEIGHT",
    "NEGLIGIBLE_MULTI_RETURN",
    "NEGLIGIBLE_CPA",
    "REALISTIC_PENETRATION",
    "APPROXIMATE_FACTOR",
    "VOXEL_RATIO",
    "STUDY_REFERENCE_MULTI_RETURN",
    "FINE_ULS_OVERESTIMATE",
    "TABLE5",
    "negligible",
]


@dataclass(frozen=True)
class Tolerance:
    """A tolerance and where in the paper it comes from.

    Attributes
    ----------
    value : float
        The tolerance.
    unit : str
        Its unit: ``"m"``, ``"pp"`` (percentage points), ``"%"`` (of the mean reference value)
        or ``"x"`` (a factor).
    source : str
        The paper's words or numbers it rests on.
    """

    value: float
    unit: str
    source: str

    def text(self) -> str:
        """The tolerance as the findings table states it."""
        unit = {"pp": " pp", "m": " m", "%": " % of the mean reference", "x": "×"}[self.unit]
        return f"±{self.value:g}{unit}" if self.unit != "x" else f"within a factor {self.value:g}"


#: metrics that are heights (m); the negligible effect of :data:`NEGLIGIBLE_HEIGHT` applies
HEIGHT_METRICS = ("hmin", "hmean", "hsd", "height", "cbh", "p01", "p05", "p10", "p20", "p30", "p40", "p50",
                  "p60", "p70", "p80", "p90", "p95", "p99")

NEGLIGIBLE_HEIGHT = Tolerance(
    0.1, "m", "the study measures crown heights in 0.1 m slices (CBH, Table 4): a change within one slice "
              "is below what it resolves")
NEGLIGIBLE_MULTI_RETURN = Tolerance(
    5.0, "pp", "the smallest difference of multiple-return shares the study reports as a finding: reference "
               "ULS conifers 33.1 % vs broadleaf 28.1 %")
NEGLIGIBLE_CPA = Tolerance(
    10.0, "%", "the smallest relative error the study names: scaled voxels give an Hsd ≈ 10 % too low")
REALISTIC_PENETRATION = Tolerance(
    8.0, "pp", "the smallest multiple-return error the study calls an overestimation: 0.02 m voxels, ULS "
               "conifers ≈ +8 pp")
APPROXIMATE_FACTOR = Tolerance(
    2.0, "x", "the study's voxel ratio is ≈ 50× over the models and up to 100× per target tree: its own "
              "spread is a factor 2")

#: the study's voxel ratio, 0.02 m fixed over scaled models
VOXEL_RATIO = 50.0
#: the study's reference multiple-return shares (%): (platform, group) → mean over the target trees
STUDY_REFERENCE_MULTI_RETURN = {("als", "conifer"): 73.4, ("als", "broadleaf"): 55.9,
                                ("uls", "conifer"): 33.1, ("uls", "broadleaf"): 28.1}
#: how far 0.02 m voxels overestimate the ULS multiple-return share (pp), by group
FINE_ULS_OVERESTIMATE = {"conifer": 8.0, "broadleaf": 20.0}

#: Table 5 by the study's method: (kind, size or shift) → (model generation, voxels, penetration,
#: CBH/CPA accuracy); None where the table states nothing
TABLE5 = {
    ("fixed", 0.25): ("simple", "few", "strongly underestimated", "low"),
    ("fixed", 0.10): ("simple", None, "underestimated", "rather low"),
    ("fixed", 0.05): ("simple", "many", "realistic", "medium"),
    ("fixed", 0.02): ("simple", "very many", "overestimated", "high"),
    ("scaled", "none"): ("complex", "few", "realistic", "high"),
    ("scaled", "random"): ("complex", "few", "realistic", "high"),
    ("scaled", "cog"): ("very complex", "few", "realistic", "high"),
}


def negligible(metric: str) -> Tolerance | None:
    """The negligible effect of a metric, or None for a metric the paper gives none for.

    Parameters
    ----------
    metric : str
        A column of :data:`vlsforest.metrics.METRIC_COLUMNS`.

    Returns
    -------
    Tolerance or None
        Heights: :data:`NEGLIGIBLE_HEIGHT`; the multiple-return share:
        :data:`NEGLIGIBLE_MULTI_RETURN`; CPA: :data:`NEGLIGIBLE_CPA` (relative).
    """
    if metric in HEIGHT_METRICS:
        return NEGLIGIBLE_HEIGHT
    if metric == "multi_return_pct":
        return NEGLIGIBLE_MULTI_RETURN
    if metric == "cpa":
        return NEGLIGIBLE_CPA
    return None
