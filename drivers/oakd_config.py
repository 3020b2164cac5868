"""Configuration of the OAK-D adapter, importable without ``depthai``.

Kept apart from :mod:`drivers.oakd` so that reading or checking the service's
configuration does not import the vendor library.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

Preset = Literal["DEFAULT", "ACCURACY", "DENSITY", "FAST_ACCURACY", "FAST_DENSITY", "ROBOTICS"]
Median = Literal["off", "3x3", "5x5", "7x7"]


class OakdConfig(BaseModel):
    """Configuration of the OAK-D: the stereo pipeline, the host queues and the reconnect
    backoff (waits doubling from ``reconnect_backoff_min`` up to ``reconnect_backoff_max``)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    device: str | None = Field(None, description="device id or name; None = the first found")
    width: int = Field(640, gt=0)
    height: int = Field(400, gt=0)
    fps: float = Field(30.0, gt=0.0)
    preset: Preset = "DEFAULT"
    confidence_threshold: int = Field(200, ge=0, le=255, description="higher keeps more pixels")
    left_right_check: bool = True
    left_right_check_threshold: int = Field(5, ge=0, le=128)
    subpixel: bool = True
    subpixel_fractional_bits: Literal[3, 4, 5] = 3
    extended_disparity: bool = False
    median_filter: Median = "off"
    output_right: bool = True
    output_disparity: bool = True
    baseline_m: float = Field(0.075, gt=0.0, description="used when the calibration has none")
    hfov_deg: float = Field(72.0, gt=0.0, lt=180.0, description="used without calibration")
    queue_size: int = Field(4, ge=1, description="device -> host queue length per stream")
    buffer: int = Field(2, ge=1, description="assembled frames kept for read(); older dropped")
    stale_after: float = Field(1.0, gt=0.0, description="s without a frame -> degraded")
    reconnect_backoff_min: float = Field(0.5, gt=0.0)
    reconnect_backoff_max: float = Field(10.0, gt=0.0)
