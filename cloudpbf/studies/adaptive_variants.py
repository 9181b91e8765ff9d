"""An adaptive variant of a cloud scene: its refinement criterion, finest level, split/merge thresholds and
schedule, as scene overrides.  The adaptive-pareto study runs many (cloudpbf.studies.adaptive_pareto); Table 1
times the best one it found (cloudpbf.studies.table1).  Spacings are m; levels follow section 5.2 of the paper
(h_l = h0 2^(-l/3))."""
from __future__ import annotations

from dataclasses import dataclass

from pbf_cuda.scene import Scene

DEFAULT_MAX_LEVEL = 3
"""The adaptive scenes' finest level (the spacing halves every 3 levels)."""

VERDICT = "adaptive_verdict.json"
"""The adaptive-pareto study's verdict for the growing cloud, in OUT/data: its ``best`` names the best variant."""


def finest_spacing(spacing_m: float, max_level: float) -> float:
    """The finest particles' spacing, m, of level-0 spacing `spacing_m` (h_l = h0 2^(-l/3), section 5.2)."""
    return spacing_m * 2.0 ** (-max_level / 3.0)


@dataclass(frozen=True)
class Config:
    """One configuration of the study (all its seeds share it)."""
    name: str          # uniform-68m, paper-54m, lookahead-68m, reference-27m
    kind: str          # uniform | adaptive | reference
    spacing_m: float   # particle spacing (adaptive: level 0)
    criterion: str     # "" for uniform runs
    max_level: int = 0              # adaptive: the finest level (spacing halves every 3 levels); 0 for uniform
    threshold_scale: float = 1.0    # adaptive: eq. 20's split and merge thresholds (alpha, beta) times this
    adapt_every: int = 0            # adaptive: split and merge every this many steps; 0: the scene's own
    pair_kernel: str = ""           # adaptive: adaptive.pair_kernel; "": the scene's own (eq. 19)
    overrides: tuple = ()           # adaptive: further scene overrides, ((key, value), ...)

    @property
    def finest_spacing_m(self) -> float:
        return finest_spacing(self.spacing_m, self.max_level)

    def adaptive_overrides(self, base: Scene) -> dict:
        """Overrides of `base` (an adaptive scene) for this variant: criterion, finest level, scaled thresholds."""
        if self.kind != "adaptive":
            return {}
        over = {"adaptive.criterion": self.criterion, "adaptive.max_level": self.max_level}
        if self.threshold_scale != 1.0:
            over |= {"adaptive.split_threshold": base.adaptive.split_threshold * self.threshold_scale,
                     "adaptive.merge_threshold": base.adaptive.merge_threshold * self.threshold_scale}
        if self.adapt_every:
            over["adaptive.every"] = self.adapt_every
        if self.pair_kernel:
            over["adaptive.pair_kernel"] = self.pair_kernel
        return over | dict(self.overrides)


def variant_name(criterion: str, spacing: float, max_level: int, threshold_scale: float, adapt_every: int = 0,
                 pair_kernel: str = "") -> str:
    """'thermal-68m', 'thermal-68m-L4' (finest level 4), 'thermal-54m-t0.25' (thresholds times 0.25),
    'thermal-68m-L4-t0.25-e4' (split and merge every 4 steps), '...-km' (the kernel at the pair's mean radius)."""
    name = f"{criterion}-{spacing:g}m"
    if max_level != DEFAULT_MAX_LEVEL:
        name += f"-L{max_level}"
    if threshold_scale != 1.0:
        name += f"-t{threshold_scale:g}"
    if adapt_every:
        name += f"-e{adapt_every}"
    if pair_kernel == "mean_radius":
        name += "-km"
    return name
