"""What a cmcan model file declares about itself (ONNX ``metadata_props``), read and checked."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from typing import Any

FORMAT = "cmcan-graybox/1"
INPUT_NAME = "x"
OUTPUT_PRED = "motor_speed_pred_rpm"
OUTPUT_WHITEBOX = "motor_speed_whitebox_rpm"


class ModelError(ValueError):
    """A model file cannot be used; ``str()`` names the file and what does not match."""


@dataclass(frozen=True)
class ModelMeta:
    format: str
    model_version: str
    inputs: list[dict[str, Any]]  # [{"name", "unit", "index"}] in input order
    outputs: list[dict[str, Any]]
    motor_disp_cc: float
    eta_vol: float
    envelope: dict[str, list[float]]  # input name -> [min, max] over the steady training points
    residual_stats: dict[str, float]  # on D_tst
    training: dict[str, Any]  # fingerprint, sizes, split times, source

    def to_props(self) -> dict[str, str]:
        return {f"cmcan.{k}": json.dumps(v) for k, v in asdict(self).items()}

    @classmethod
    def from_props(cls, props: dict[str, str], source: str) -> ModelMeta:
        fields = list(cls.__dataclass_fields__)
        missing = [f for f in fields if f"cmcan.{f}" not in props]
        if missing:
            raise ModelError(f"{source}: not a cmcan model: metadata lacks {', '.join('cmcan.' + m for m in missing)}")
        try:
            values = {f: json.loads(props[f"cmcan.{f}"]) for f in fields}
        except json.JSONDecodeError as exc:
            raise ModelError(f"{source}: corrupt metadata: {exc}") from None
        meta = cls(**values)
        if meta.format != FORMAT:
            raise ModelError(f"{source}: model format {meta.format!r}, this cmcan reads {FORMAT!r}")
        return meta

    @property
    def input_names(self) -> list[str]:
        return [d["name"] for d in sorted(self.inputs, key=lambda d: d["index"])]
