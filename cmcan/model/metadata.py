"""What a cmcan model file declares about itself (ONNX ``metadata_props``), read and checked."""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from typing import Any

from cmcan.errors import CmcanError, Kind
from cmcan.roles import QUANTITIES, UNITS

FORMAT = "cmcan-graybox/2"
INPUT_NAME = "x"
OUTPUT_PRED = "predicted"
OUTPUT_PHYSICS = "physics"
OUTPUT_WHITEBOX = "whitebox"
QUANTITY_UNITS = {q: UNITS[q] for q in QUANTITIES}  # what a model file may predict, in its unit


class ModelError(CmcanError, ValueError):
    """A model file cannot be used; ``str()`` names the file and what does not match."""

    kind = Kind.CONFIG


@dataclass(frozen=True)
class ModelMeta:
    format: str
    model_version: str
    inputs: list[dict[str, Any]]  # [{"name", "unit", "index"}] in input order
    quantity: dict[str, Any]  # {"role": "motor_speed_rpm" | "flow_lpm", "unit"}
    outputs: list[dict[str, Any]]
    motor_disp_cc: float | None  # V_M of a closed circuit; None when the quantity is flow
    oil: dict[str, float]  # {"nu40_cst", "nu100_cst"}: the viscosity law of the laminar term
    physics: dict[str, Any]  # {"coefficients": {term: value}, "eta_vol"}
    correction: dict[str, Any]  # {"bound_lpm", "basis", "ridge", "fade_span"}
    envelope: dict[str, list[float]]  # input name -> [min, max] over the steady training points
    residual_stats: dict[str, Any]  # on D_tst
    training: dict[str, Any]  # fingerprint, sizes, split times, source

    def to_props(self) -> dict[str, str]:
        return {f"cmcan.{k}": json.dumps(v) for k, v in asdict(self).items()}

    @classmethod
    def from_props(cls, props: dict[str, str], source: str) -> ModelMeta:
        fields = list(cls.__dataclass_fields__)
        fmt = props.get("cmcan.format")
        if fmt is not None and fmt != json.dumps(FORMAT):
            try:
                found = json.loads(fmt)
            except json.JSONDecodeError:
                found = fmt
            raise ModelError(
                f"{source}: model format {found!r}, this cmcan reads {FORMAT!r}; retrain it with cmcan train"
            )
        missing = [f for f in fields if f"cmcan.{f}" not in props]
        if missing:
            raise ModelError(f"{source}: not a cmcan model: metadata lacks {', '.join('cmcan.' + m for m in missing)}")
        values = {}
        for f in fields:
            try:
                values[f] = json.loads(props[f"cmcan.{f}"])
            except json.JSONDecodeError as exc:
                raise ModelError(f"{source}: metadata cmcan.{f} is not valid JSON: {exc}") from None
        meta = cls(**values)
        meta.check(source)
        return meta

    def check(self, source: str) -> None:
        """Types and values of the fields the runtime relies on: a wrong one is named, not a crash later."""

        def bad(field: str, expected: str, got: Any) -> ModelError:
            return ModelError(f"{source}: metadata cmcan.{field}: expected {expected}, got {got!r}")

        if not isinstance(self.inputs, list) or not self.inputs:
            raise bad("inputs", "a list of {name, unit, index}", self.inputs)
        for i, d in enumerate(self.inputs):
            if not isinstance(d, dict) or not isinstance(d.get("name"), str) or not isinstance(d.get("unit"), str):
                raise bad(f"inputs[{i}]", "{name: str, unit: str, index: int}", d)
            if not isinstance(d.get("index"), int) or isinstance(d.get("index"), bool):
                raise bad(f"inputs[{i}].index", "an integer", d.get("index"))
        if sorted(d["index"] for d in self.inputs) != list(range(len(self.inputs))):
            raise bad("inputs", "indices 0..n-1, each once", [d["index"] for d in self.inputs])
        q = self.quantity
        if not isinstance(q, dict) or q.get("role") not in QUANTITY_UNITS or q.get("unit") != QUANTITY_UNITS[q["role"]]:
            raise bad("quantity", f"one of {QUANTITY_UNITS} as {{role, unit}}", q)
        if q["role"] == "motor_speed_rpm" and not _positive(self.motor_disp_cc):
            raise bad("motor_disp_cc", "a positive number (cm3/rev) for a motor-speed model", self.motor_disp_cc)
        if not isinstance(self.model_version, str):
            raise bad("model_version", "a string", self.model_version)
        if not isinstance(self.outputs, list) or not all(
            isinstance(o, dict) and isinstance(o.get("name"), str) and isinstance(o.get("unit"), str)
            for o in self.outputs
        ):
            raise bad("outputs", "a list of {name: str, unit: str}", self.outputs)
        if not isinstance(self.physics, dict) or not isinstance(self.physics.get("coefficients"), dict):
            raise bad("physics", "a mapping with the coefficients of the physics terms", self.physics)
        if not all(_finite(v) for v in self.physics["coefficients"].values()):
            raise bad("physics.coefficients", "finite numbers", self.physics["coefficients"])
        if not isinstance(self.correction, dict):
            raise bad("correction", "a mapping", self.correction)
        if not isinstance(self.envelope, dict):
            raise bad("envelope", "a mapping of input name to [min, max]", self.envelope)
        for name, rng in self.envelope.items():
            if not (isinstance(rng, list) and len(rng) == 2 and all(_finite(v) for v in rng) and rng[0] <= rng[1]):
                raise bad(f"envelope.{name}", "[min, max] with min <= max", rng)
        names = {d["name"] for d in self.inputs}
        if set(self.envelope) != names:
            raise bad("envelope", f"[min, max] of each input ({', '.join(sorted(names))})", sorted(self.envelope))
        if not isinstance(self.oil, dict) or not all(_positive(self.oil.get(k)) for k in ("nu40_cst", "nu100_cst")):
            raise bad("oil", "{nu40_cst, nu100_cst} in cSt", self.oil)
        if not isinstance(self.training, dict) or not isinstance(self.residual_stats, dict):
            raise bad("training", "mappings for training and residual_stats", self.training)

    @property
    def input_names(self) -> list[str]:
        return [d["name"] for d in sorted(self.inputs, key=lambda d: d["index"])]

    @property
    def quantity_role(self) -> str:
        return str(self.quantity["role"])


def _finite(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _positive(v: Any) -> bool:
    return _finite(v) and v > 0
