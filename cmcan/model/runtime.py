"""Running a cmcan model with onnxruntime on the gateway: CPU, one thread, float64, metadata checked."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from cmcan.errors import Kind
from cmcan.model import digest
from cmcan.model.metadata import INPUT_NAME, OUTPUT_PHYSICS, OUTPUT_PRED, OUTPUT_WHITEBOX, ModelError, ModelMeta
from cmcan.oil import Oil
from cmcan.roles import MODEL_INPUTS, MODEL_UNITS

# onnxruntime (1.2x and later) records usage events in ~/.cache/Microsoft/DeveloperTools unless told
# not to, and warns on every start where the home is not writable (a service user's): a gateway
# sends nothing anywhere it was not configured to. Read when onnxruntime sets up, so set before any
# model loads; a value the user set stays.
os.environ.setdefault("ORT_DISABLE_TELEMETRY", "1")


class GrayBoxModel:
    """A loaded model: ``predict`` for batches, ``predict_one`` for the monitor's per-tick call."""

    def __init__(
        self,
        path: str | Path,
        expected_inputs: dict[str, str] | None = None,
        motor_disp_cc: float | None = None,
        quantity: str | None = None,
        oil: Oil | None = None,
    ) -> None:
        import onnxruntime as ort

        self.path = Path(path)
        if not self.path.exists():
            raise ModelError(f"{self.path}: model file not found", Kind.NO_INPUT)
        # Read once: the bytes whose digest is checked are the bytes onnxruntime loads.
        try:
            blob = self.path.read_bytes()
        except OSError as exc:
            raise ModelError(f"{self.path}: cannot read the model file: {exc.strerror}", Kind.NO_INPUT) from None
        recorded, malformed = _recorded_digest(blob, str(self.path))  # before onnxruntime: corruption named so
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = 1
        opts.inter_op_num_threads = 1
        opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        opts.log_severity_level = 3
        try:
            self.session = ort.InferenceSession(blob, sess_options=opts, providers=["CPUExecutionProvider"])
        except Exception as exc:  # onnxruntime raises its own exception types for bad files
            raise ModelError(f"{self.path}: not a loadable ONNX model: {exc}") from None
        if malformed:  # onnxruntime took what the digest's walk could not: no digest to trust
            raise ModelError(f"{self.path}: not a well-formed model file: {malformed}")
        try:
            props = self.session.get_modelmeta().custom_metadata_map
        except (UnicodeDecodeError, RuntimeError) as exc:  # metadata bytes that are not text
            raise ModelError(f"{self.path}: metadata is not readable: {exc}") from None
        self.meta = ModelMeta.from_props(props, str(self.path))
        if recorded is None:  # a cmcan model (the line above named a foreign file), from an older cmcan
            raise ModelError(
                f"{self.path}: no digest of its weights ({digest.KEY}): written by an older cmcan; "
                "retrain it with cmcan train (python -m cmcan.rebuild_default for the shipped model)"
            )
        self._check(expected_inputs or MODEL_UNITS, motor_disp_cc)
        self._check_machine(quantity, oil)
        self._outputs = [OUTPUT_PRED, OUTPUT_WHITEBOX]
        # The per-tick call binds preallocated arrays once: onnxruntime reads and writes them in place,
        # which saves the conversions of ``run`` (about 3 us of a 15 us call).
        self._one = np.zeros((1, len(MODEL_INPUTS)), dtype=np.float64)
        self._one_pred = np.zeros((1, 1), dtype=np.float64)
        self._one_wb = np.zeros((1, 1), dtype=np.float64)
        self._values = [ort.OrtValue.ortvalue_from_numpy(a) for a in (self._one, self._one_pred, self._one_wb)]
        self._binding = self.session.io_binding()
        self._binding.bind_ortvalue_input(INPUT_NAME, self._values[0])
        self._binding.bind_ortvalue_output(OUTPUT_PRED, self._values[1])
        self._binding.bind_ortvalue_output(OUTPUT_WHITEBOX, self._values[2])

    def _check(self, expected: dict[str, str], motor_disp_cc: float | None) -> None:
        src = str(self.path)
        declared = {d["name"]: d["unit"] for d in self.meta.inputs}
        names = self.meta.input_names
        if names != list(expected):
            raise ModelError(f"{src}: model inputs are {names}, the configuration feeds {list(expected)}")
        for name, unit in expected.items():
            if declared[name] != unit:
                raise ModelError(f"{src}: input {name!r} is in {declared[name]!r}, the configuration gives {unit!r}")
        graph_in = self.session.get_inputs()
        if len(graph_in) != 1 or graph_in[0].name != INPUT_NAME or graph_in[0].shape[-1] != len(names):
            raise ModelError(f"{src}: graph input must be {INPUT_NAME!r} of shape [N, {len(names)}]")
        outs = {o.name for o in self.session.get_outputs()}
        if not {OUTPUT_PRED, OUTPUT_PHYSICS, OUTPUT_WHITEBOX} <= outs:
            need = ", ".join(repr(n) for n in (OUTPUT_PRED, OUTPUT_PHYSICS, OUTPUT_WHITEBOX))
            raise ModelError(f"{src}: graph outputs {sorted(outs)} lack one of {need}")
        if graph_in[0].type != "tensor(double)":
            raise ModelError(f"{src}: graph input {INPUT_NAME!r} is {graph_in[0].type}, expected tensor(double)")
        if (
            motor_disp_cc is not None
            and self.meta.motor_disp_cc is not None
            and abs(self.meta.motor_disp_cc - motor_disp_cc) > 1e-6 * motor_disp_cc
        ):
            raise ModelError(
                f"{src}: trained for a motor displacement of {self.meta.motor_disp_cc:g} cm3/rev, "
                f"the configuration says {motor_disp_cc:g} cm3/rev"
            )

    def _check_machine(self, quantity: str | None, oil: Oil | None) -> None:
        """The machine the configuration describes is the one the model learned: its output quantity
        and the oil whose viscosity law the laminar leakage term uses."""
        src = str(self.path)
        if quantity is not None and self.meta.quantity_role != quantity:
            raise ModelError(
                f"{src}: predicts {self.meta.quantity_role}, the configuration's drive.quantity is {quantity}"
            )
        if oil is not None:
            mine = (float(self.meta.oil["nu40_cst"]), float(self.meta.oil["nu100_cst"]))
            if any(abs(a - b) > 1e-6 * b for a, b in zip(mine, (oil.nu40_cst, oil.nu100_cst), strict=True)):
                raise ModelError(
                    f"{src}: trained for an oil of {mine[0]:g} cSt at 40 C and {mine[1]:g} cSt at 100 C, the "
                    f"configuration's oil has {oil.nu40_cst:g} and {oil.nu100_cst:g} cSt: retrain for the new oil"
                )

    @property
    def quantity(self) -> str:
        return self.meta.quantity_role

    @property
    def envelope(self) -> dict[str, tuple[float, float]]:
        return {k: (float(v[0]), float(v[1])) for k, v in self.meta.envelope.items()}

    @property
    def motor_disp_cc(self) -> float | None:
        return None if self.meta.motor_disp_cc is None else float(self.meta.motor_disp_cc)

    def predict(self, x: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """(predicted, white-box) output quantity for inputs (n, 4) in the model's input order."""
        parts = self._run(x, self._outputs)
        return parts[0], parts[1]

    def predict_parts(self, x: NDArray[np.float64]) -> dict[str, NDArray[np.float64]]:
        """Every output of the graph: predicted (gray box), physics (light gray) and white-box."""
        names = [OUTPUT_PRED, OUTPUT_PHYSICS, OUTPUT_WHITEBOX]
        return dict(zip(names, self._run(x, names), strict=True))

    def _run(self, x: NDArray[np.float64], names: list[str]) -> list[NDArray[np.float64]]:
        """The graph over rows. A row gives the same bits alone or anywhere in a batch (the graph
        hands whole vectors to its transcendental functions; tests check), so the columnar replay's
        batched calls equal the daemon's single ones."""
        xx = np.ascontiguousarray(np.atleast_2d(x), dtype=np.float64)
        if len(xx) == 0:
            return [np.empty(0) for _ in names]
        return [v[:, 0] for v in self.session.run(names, {INPUT_NAME: xx})]

    def predict_one(
        self, pump_speed_rpm: float, pump_disp_cc: float, dp_bar: float, temp_c: float
    ) -> tuple[float, float]:
        one = self._one
        one[0, 0] = pump_speed_rpm
        one[0, 1] = pump_disp_cc
        one[0, 2] = dp_bar
        one[0, 3] = temp_c
        self.session.run_with_iobinding(self._binding)
        return float(self._one_pred[0, 0]), float(self._one_wb[0, 0])


def _recorded_digest(blob: bytes, src: str) -> tuple[str | None, str]:
    """(the digest a file records if its content matches it or None if it records none, why the
    bytes are not a protobuf message or "").

    A mismatch is named before onnxruntime or the metadata see the file: a flipped bit is then called
    corruption, not a graph error or a wrong field. Bytes that are not a protobuf message are left to
    onnxruntime to name first."""
    try:
        recorded, actual = digest.recorded_and_actual(blob)
    except digest.MalformedError as exc:
        return None, str(exc)
    except ValueError as exc:
        raise ModelError(f"{src}: {exc}") from None
    if recorded is not None and recorded != actual:
        raise ModelError(
            f"{src}: the weights and metadata do not match their recorded digest ({digest.KEY}): "
            "the file is corrupt or was edited; copy it again from its source or retrain it"
        )
    return recorded, ""


def load_model(
    path: str | Path,
    expected_inputs: dict[str, str] | None = None,
    motor_disp_cc: float | None = None,
    quantity: str | None = None,
    oil: Oil | None = None,
) -> GrayBoxModel:
    return GrayBoxModel(path, expected_inputs, motor_disp_cc, quantity, oil)


def default_model_path() -> Path:
    return Path(__file__).resolve().parent / "default.onnx"
