"""The synthetic benchmark's variants (Table 1 frames, Table 2 ablations, the two-stage recipes) as plain Python: each
turns the benchmark's TrainRun into its own (bench.accuracy runs them)."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

from rafd.train.run import TrainRun


@dataclass(frozen=True)
class Variant:
    name: str
    description: str
    frames: int = 4
    enhancement: bool = True
    flow_supervision: bool = True
    flow_guidance: bool = True
    # Targets before issue 11: (sin yaw, cos yaw) and sizes as labelled, heatmap radius overlap 0.7 / floor 1.
    legacy_targets: bool = False
    flow_stride: int | None = None  # None: the recipe's (8); 4 = the paper's flow branch
    enhance_window: int | None = None  # None: the recipe's (16); 0 = the paper's Hf/2 windows
    propagation_norm: str | None = None  # None: the recipe's ("pre"); "post" = Deformable DETR's blocks
    # Two-stage training: start from the weights of this variant's model in the same out_dir (rafd-train --init).
    init: str | None = None
    freeze: tuple[str, ...] = ()  # parts that do not train (rafd-train --freeze)

    def apply(self, run: TrainRun) -> TrainRun:
        """The benchmark's training run changed as this variant says (its --init is set by the runner)."""
        legacy: dict[str, Any] = {"box_encoding": "as_labelled", "heatmap_min_overlap": 0.7, "heatmap_min_radius": 1}
        return replace(
            run,
            frames=self.frames,
            flow_stride=self.flow_stride,
            enhance_window=self.enhance_window,
            propagation_norm=self.propagation_norm,
            no_enhancement=not self.enhancement,
            no_flow_supervision=not self.flow_supervision,
            no_flow_guidance=not self.flow_guidance,
            freeze=self.freeze,
            **(legacy if self.legacy_targets else {}),
        )


# Only the fresh parts train: the propagation starts as the identity, so the model starts as the single-frame model
# and can only add what its past frames show to the features the single-frame head reads (the shipped recipe).
FRESH_ONLY = Variant(
    "rafd4_from_single_fresh_only",
    "RaFD, 4 frames, from the single-frame model, only its flow branch and propagation trained",
    init="single",
    freeze=("encoder", "head"),
)

# Table 1 (frames) and leave-one-out ablations; "baseline"/"enh_only" + no_guidance + rafd4 give the
# paper's cumulative Table 2 (baseline -> + enhancement -> + flow estimation -> + flow guidance).
VARIANTS = {
    v.name: v
    for v in (
        Variant("rafd4", "RaFD, 4 frames"),
        Variant(
            "rafd4_post_norm",
            "RaFD, 4 frames, post-norm propagation blocks (Deformable DETR's)",
            propagation_norm="post",
        ),
        # Second stage of a two-stage recipe: run after `single` in the same out_dir; `single_continued` gives the
        # single-frame model the same extra epochs, so the pair compares equal budgets.
        Variant("rafd4_from_single", "RaFD, 4 frames, initialised from the single-frame model", init="single"),
        Variant(
            "rafd4_from_single_frozen",
            "RaFD, 4 frames, from the single-frame model, its encoder frozen",
            init="single",
            freeze=("encoder",),
        ),
        FRESH_ONLY,
        # The shipped recipe with the paper's flow branch (stride 4 instead of 8): the accuracy the speed option costs.
        replace(
            FRESH_ONLY,
            name="rafd4_from_single_fresh_only_flow4",
            description=FRESH_ONLY.description + ", flow at stride 4 (the paper's)",
            flow_stride=4,
        ),
        Variant(
            "rafd2_from_single", "RaFD, 2 frames, initialised from the single-frame model", frames=2, init="single"
        ),
        Variant(
            "no_guidance_from_single",
            "4 frames, vanilla deformable attention, initialised from the single-frame model",
            flow_guidance=False,
            init="single",
        ),
        Variant("single_continued", "single frame, continued from the single-frame model", frames=1, init="single"),
        Variant(
            "rafd4_legacy_targets",
            "RaFD, 4 frames, targets as labelled (sin/cos yaw, radius 0.7 / 1)",
            legacy_targets=True,
        ),
        Variant("rafd4_paper_flow", "RaFD, 4 frames, flow branch at stride 4 (the paper's)", flow_stride=4),
        Variant("rafd4_paper_windows", "RaFD, 4 frames, Hf/2 x Wf/2 attention windows (the paper's)", enhance_window=0),
        Variant("rafd2", "RaFD, 2 frames", frames=2),
        Variant("single", "single frame (CenterFormer-style)", frames=1),
        Variant("no_enh", "4 frames, without feature enhancement", enhancement=False),
        Variant("no_flow_sup", "4 frames, flow not supervised (weight 0)", flow_supervision=False),
        Variant("no_guidance", "4 frames, vanilla deformable attention (= + flow estimation)", flow_guidance=False),
        Variant("enh_only", "4 frames, + enhancement only", flow_supervision=False, flow_guidance=False),
        Variant(
            "baseline",
            "4 frames, vanilla deformable attention, no enhancement, no flow loss",
            enhancement=False,
            flow_supervision=False,
            flow_guidance=False,
        ),
    )
}
DEFAULT_VARIANTS = ("rafd4", "rafd2", "single", "no_guidance")
