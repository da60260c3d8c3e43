"""The synthetic benchmark's variants (Table 1 frames, Table 2 ablations, the two-stage recipes): each is a few
settings of the run config (rafd.train.config) that turn the benchmark's TrainRun into its own (bench.accuracy runs
them)."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

from rafd.train.run import TrainRun


@dataclass(frozen=True)
class Variant:
    name: str
    description: str
    # dotted settings of the run config (rafd.train.config) that make this variant of the benchmark's recipe
    settings: tuple[tuple[str, Any], ...] = ()
    # Two-stage training: start from the weights of this variant's model in the same out_dir (rafd train --init).
    init: str | None = None

    def apply(self, run: TrainRun) -> TrainRun:
        """The benchmark's training run changed as this variant says (its --init is set by the runner)."""
        return replace(run, config=run.config.overridden(dict(self.settings)))


def frames(n: int) -> tuple[str, Any]:
    return ("model.num_frames", n)


NO_ENHANCEMENT = ("model.enhance.enabled", False)
NO_FLOW_SUPERVISION = ("loss.flow_weight", 0.0)
NO_FLOW_GUIDANCE = ("model.propagation.flow_guided", False)
# Targets before issue 11: (sin yaw, cos yaw) and sizes as labelled, heatmap radius overlap 0.7 / floor 1.
LEGACY_TARGETS = (
    ("model.head.box_encoding", "as_labelled"),
    ("model.targets.heatmap_min_overlap", 0.7),
    ("model.targets.heatmap_min_radius", 1),
)
PAPER_FLOW = ("model.flow.stride", 4)  # the recipe's is 8
PAPER_WINDOWS = ("model.enhance.window", 0)  # the recipe's is 16 cells; 0 = the paper's Hf/2
POST_NORM = ("model.propagation.norm", "post")  # the recipe's is "pre"


# Only the fresh parts train: the propagation starts as the identity, so the model starts as the single-frame model
# and can only add what its past frames show to the features the single-frame head reads (the shipped recipe).
FRESH_ONLY = Variant(
    "rafd4_from_single_fresh_only",
    "RaFD, 4 frames, from the single-frame model, only its flow branch and propagation trained",
    (("train.freeze", ("encoder", "head")),),
    init="single",
)

# Table 1 (frames) and leave-one-out ablations; "baseline"/"enh_only" + no_guidance + rafd4 give the
# paper's cumulative Table 2 (baseline -> + enhancement -> + flow estimation -> + flow guidance).
VARIANTS = {
    v.name: v
    for v in (
        Variant("rafd4", "RaFD, 4 frames"),
        Variant("rafd4_post_norm", "RaFD, 4 frames, post-norm propagation blocks (Deformable DETR's)", (POST_NORM,)),
        # Second stage of a two-stage recipe: run after `single` in the same out_dir; `single_continued` gives the
        # single-frame model the same extra epochs, so the pair compares equal budgets.
        Variant("rafd4_from_single", "RaFD, 4 frames, initialised from the single-frame model", init="single"),
        Variant(
            "rafd4_from_single_frozen",
            "RaFD, 4 frames, from the single-frame model, its encoder frozen",
            (("train.freeze", ("encoder",)),),
            init="single",
        ),
        FRESH_ONLY,
        # The shipped recipe with the paper's flow branch (stride 4 instead of 8): the accuracy the speed option costs.
        replace(
            FRESH_ONLY,
            name="rafd4_from_single_fresh_only_flow4",
            description=FRESH_ONLY.description + ", flow at stride 4 (the paper's)",
            settings=(*FRESH_ONLY.settings, PAPER_FLOW),
        ),
        Variant(
            "rafd2_from_single", "RaFD, 2 frames, initialised from the single-frame model", (frames(2),), init="single"
        ),
        Variant(
            "no_guidance_from_single",
            "4 frames, vanilla deformable attention, initialised from the single-frame model",
            (NO_FLOW_GUIDANCE,),
            init="single",
        ),
        Variant("single_continued", "single frame, continued from the single-frame model", (frames(1),), init="single"),
        Variant(
            "rafd4_legacy_targets", "RaFD, 4 frames, targets as labelled (sin/cos yaw, radius 0.7 / 1)", LEGACY_TARGETS
        ),
        Variant("rafd4_paper_flow", "RaFD, 4 frames, flow branch at stride 4 (the paper's)", (PAPER_FLOW,)),
        Variant("rafd4_paper_windows", "RaFD, 4 frames, Hf/2 x Wf/2 attention windows (the paper's)", (PAPER_WINDOWS,)),
        Variant("rafd2", "RaFD, 2 frames", (frames(2),)),
        Variant("single", "single frame (CenterFormer-style)", (frames(1),)),
        Variant("no_enh", "4 frames, without feature enhancement", (NO_ENHANCEMENT,)),
        Variant("no_flow_sup", "4 frames, flow not supervised (weight 0)", (NO_FLOW_SUPERVISION,)),
        Variant("no_guidance", "4 frames, vanilla deformable attention (= + flow estimation)", (NO_FLOW_GUIDANCE,)),
        Variant("enh_only", "4 frames, + enhancement only", (NO_FLOW_SUPERVISION, NO_FLOW_GUIDANCE)),
        Variant(
            "baseline",
            "4 frames, vanilla deformable attention, no enhancement, no flow loss",
            (NO_ENHANCEMENT, NO_FLOW_SUPERVISION, NO_FLOW_GUIDANCE),
        ),
    )
}
DEFAULT_VARIANTS = ("rafd4", "rafd2", "single", "no_guidance")
