"""The served model: ONNX metadata, config and what the service accepts."""

from __future__ import annotations

from fastapi import APIRouter, Depends

from rafd.scans.native import NATIVE_FORMAT_RULE, NATIVE_FORMATS, SENSOR_SHAPE, NativeShape
from rafd.scans.polar import RADIATE_POLAR_SHAPE, accepts_polar
from service.dependencies import get_service
from service.pipeline.detector import DetectService
from service.schemas import FarThresholdOut, FullScanOut, ModelInfo, RuntimeOut

router = APIRouter(tags=["model"])


def native_description(shape: NativeShape = SENSOR_SHAPE) -> dict[str, object]:
    """What GET /model says about native scans (rafd.scans.native): the shape rule and each dataset's range bin."""
    return {
        "rows": f"{shape.rows_rule()} (Oxford and Boreas: 400; RAFD_NATIVE_MAX_AZIMUTHS)",
        "columns": f"{shape.columns_rule()} (RAFD_NATIVE_MAX_RANGE_BINS)",
        "formats": {name: fmt.range_bin_m for name, fmt in NATIVE_FORMATS.items()},
        "format_rule": NATIVE_FORMAT_RULE,
    }


@router.get("/model", response_model=ModelInfo)
async def model_info(service: DetectService = Depends(get_service)) -> ModelInfo:
    cfg = service.config
    far = service.score_threshold.far_json()
    return ModelInfo(
        metadata=dict(service.runner.metadata),
        config=cfg.to_dict(),
        input_size=cfg.input_size,
        num_frames=cfg.num_frames,
        feature_size=cfg.feature_size,
        cell_size_m=cfg.cell_size,
        resolution_m_per_px=cfg.resolution,
        class_names=list(cfg.class_names),
        accepted_image_sizes=list(service.accepted_sizes),
        # a Navtech_Polar scan [range rows, azimuth columns] is accepted where a full RADIATE scan is
        accepted_polar_shape=list(RADIATE_POLAR_SHAPE) if accepts_polar(cfg.input_size, cfg.resolution) else None,
        accepted_native=native_description(service.native_shape)
        if accepts_polar(cfg.input_size, cfg.resolution)
        else None,
        score_threshold=service.score_threshold.near,
        far_score_threshold=None if far is None else FarThresholdOut.model_validate(far),
        # how the graph runs: runtime, precision, threads per run, concurrent runs, start-up timings
        runtime=RuntimeOut.model_validate(service.runner.describe()),
        full_scan=None if service.full_scan is None else FullScanOut.model_validate(service.full_scan_cost()),
    )
