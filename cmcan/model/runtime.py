"""Running a cmcan model with onnxruntime on the gateway: CPU, one thread, float64, metadata checked.

Loading is bounded, so ``check`` or a reload onto a wrong (or hostile) file cannot hang: the file is
read only if it is a regular file of at most ``MAX_MODEL_BYTES``; its digest is checked and its graph's
operators are read from the bytes (:func:`cmcan.model.digest.graph_content`) before onnxruntime sees
it: only the operators cmcan's exporter writes (:data:`OPERATORS`) are accepted, so control flow
(Loop, Scan, If: a loop's trip count is data), custom domains and model-local functions are refused;
onnxruntime's constant folding is off (it would run constant parts of the graph while the session is
made, outside any time limit; cmcan's graphs have none); and a probe prediction at the corners of the
training envelope runs in a session whose memory is capped (``PROBE_MEMORY_BYTES``) and is cancelled
(``RunOptions.terminate``, set from a timer thread) when it takes longer than ``budget_s``.
"""

from __future__ import annotations

import os
import stat
import threading
from pathlib import Path
from typing import Any

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

# The operators cmcan.model.graph writes (tests/test_model_guards.py keeps the two in step), all of the
# default domain. Each costs time in proportion to its tensors; none repeats or branches.
OPERATORS = frozenset(
    {
        "Abs", "Add", "Clip", "Concat", "Div", "Exp", "Expand", "Gemm", "Log", "MatMul", "Mul",
        "ReduceSumSquare", "Relu", "Sign", "Slice", "Split", "Sqrt", "Sub",
    }
)  # fmt: skip
_DEFAULT_DOMAINS = ("", "ai.onnx")
MAX_MODEL_BYTES = 64 << 20  # cmcan's models are a few kB; their weights grow with the basis, not past this
PROBE_BUDGET_S = 2.0  # the probe's 9 rows take well under a millisecond on a gateway
PROBE_MEMORY_BYTES = 64 << 20  # what the probe's session may allocate (cmcan's graph: a few kB per row)
_NO_FOLDING = ["ConstantFolding"]
_probe_arena: bool | None = None  # whether the capped allocator is registered (once per process)


class GrayBoxModel:
    """A loaded model: ``predict`` for batches, ``predict_one`` for the monitor's per-tick call."""

    def __init__(
        self,
        path: str | Path,
        expected_inputs: dict[str, str] | None = None,
        motor_disp_cc: float | None = None,
        quantity: str | None = None,
        oil: Oil | None = None,
        budget_s: float = PROBE_BUDGET_S,
    ) -> None:
        import onnxruntime as ort

        self.path = Path(path)
        if not self.path.exists():
            raise ModelError(f"{self.path}: model file not found", Kind.NO_INPUT)
        # Read once: the bytes whose digest is checked are the bytes onnxruntime loads.
        blob = _read_model(self.path)
        recorded, malformed = _recorded_digest(blob, str(self.path))  # before onnxruntime: corruption named so
        if not malformed:  # what the file is, then what its graph does, before onnxruntime parses it
            props = digest.metadata_props(blob)
            if props is not None:
                ModelMeta.from_props(props, str(self.path))  # a foreign file is named as such first
            check_operators(blob, str(self.path))
        try:
            self.session = ort.InferenceSession(
                blob, sess_options=_options(), providers=["CPUExecutionProvider"], disabled_optimizers=_NO_FOLDING
            )
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
        _probe(blob, self.probe_rows(), str(self.path), budget_s)
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

    def probe_rows(self) -> NDArray[np.float64]:
        """The centre of the training envelope and each input at its minimum and its maximum with the
        others at the centre (the points ``cmcan.assemble.check_predictions`` judges)."""
        env = self.envelope
        centre = [(env[r][0] + env[r][1]) / 2.0 for r in MODEL_INPUTS]
        rows = [centre]
        for i, r in enumerate(MODEL_INPUTS):
            for bound in env[r]:
                row = list(centre)
                row[i] = bound
                rows.append(row)
        return np.array(rows, dtype=np.float64)

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


def _read_model(path: Path) -> bytes:
    """The file's bytes if it is a regular file of at most MAX_MODEL_BYTES (a FIFO or a device neither
    blocks nor fills memory)."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError as exc:
        kind = Kind.NO_PERMISSION if isinstance(exc, PermissionError) else Kind.NO_INPUT
        raise ModelError(f"{path}: cannot read the model file: {exc.strerror}", kind) from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise ModelError(f"{path}: not a regular file, expected an ONNX model file")
        if st.st_size > MAX_MODEL_BYTES:
            raise ModelError(f"{path}: {st.st_size} bytes, more than a cmcan model holds ({MAX_MODEL_BYTES})")
        chunks, n = [], 0
        while n <= MAX_MODEL_BYTES and (chunk := os.read(fd, 1 << 20)):
            chunks.append(chunk)
            n += len(chunk)
    except OSError as exc:
        raise ModelError(f"{path}: cannot read the model file: {exc.strerror}", Kind.IO_ERROR) from None
    finally:
        os.close(fd)
    if n > MAX_MODEL_BYTES:
        raise ModelError(f"{path}: more than {MAX_MODEL_BYTES} bytes, more than a cmcan model holds")
    return b"".join(chunks)


def check_operators(blob: bytes, src: str) -> None:
    """Refuse a graph with an operator cmcan's exporter does not write (control flow among them), a
    subgraph, model-local functions or training graphs: read from the bytes, before onnxruntime."""
    try:
        g = digest.graph_content(blob)
    except digest.MalformedError as exc:
        raise ModelError(f"{src}: not a well-formed model file: {exc}") from None
    bad = sorted(
        {
            op if dom in _DEFAULT_DOMAINS else f"{dom}:{op}"
            for dom, op in g.ops
            if dom not in _DEFAULT_DOMAINS or op not in OPERATORS
        }
    )
    if bad:
        shown = ", ".join(repr(b[:40]) for b in bad[:5]) + (f" and {len(bad) - 5} more" if len(bad) > 5 else "")
        raise ModelError(
            f"{src}: the graph uses {shown}, not an operator of a cmcan model ({', '.join(sorted(OPERATORS))}); "
            "control flow (Loop, Scan, If) and other operators are refused"
        )
    if g.subgraphs or g.functions or g.training_info:
        what = "subgraphs" if g.subgraphs else "model-local functions" if g.functions else "training graphs"
        raise ModelError(f"{src}: the file holds {what}, which a cmcan model never has")


def _options(**config: str) -> Any:
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1
    opts.inter_op_num_threads = 1
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    opts.log_severity_level = 3
    for key, value in config.items():
        opts.add_session_config_entry(key, value)
    return opts


def _capped_arena() -> bool:
    """Register, once per process, the capped allocator probe sessions use; False where this
    onnxruntime cannot (the probe is then bounded in time only)."""
    global _probe_arena
    if _probe_arena is None:
        import onnxruntime as ort

        try:
            info = ort.OrtMemoryInfo("Cpu", ort.OrtAllocatorType.ORT_ARENA_ALLOCATOR, 0, ort.OrtMemType.DEFAULT)
            ort.create_and_register_allocator(info, ort.OrtArenaCfg(PROBE_MEMORY_BYTES, 1, -1, -1))
            _probe_arena = True
        except Exception:  # an older onnxruntime, or one registered by someone else: time bound only
            _probe_arena = False
    return _probe_arena


def _probe(blob: bytes, rows: NDArray[np.float64], src: str, budget_s: float) -> None:
    """Run the graph once on ``rows`` in a session of its own with capped memory, cancelled after
    ``budget_s``: a graph that is slow or asks for much memory is refused before the monitor uses it."""
    import onnxruntime as ort

    capped = _capped_arena()
    opts = _options(**({"session.use_env_allocators": "1"} if capped else {}))
    opts.log_severity_level = 4  # the failure is ours to report, in one line
    try:
        session = ort.InferenceSession(blob, sess_options=opts, providers=["CPUExecutionProvider"],
                                       disabled_optimizers=_NO_FOLDING)  # fmt: skip
    except Exception as exc:
        raise ModelError(f"{src}: not a loadable ONNX model: {exc}") from None
    run = ort.RunOptions()
    run.log_severity_level = 4
    timer = threading.Timer(budget_s, lambda: setattr(run, "terminate", True))
    timer.daemon = True
    timer.start()
    try:
        session.run([OUTPUT_PRED, OUTPUT_WHITEBOX], {INPUT_NAME: rows}, run)
    except Exception as exc:
        text = str(exc)
        if run.terminate or "terminate flag" in text:
            raise ModelError(
                f"{src}: a prediction did not finish within {budget_s:g} s (a cmcan model takes well under a "
                "millisecond): refused"
            ) from None
        if "Available memory" in text or "Failed to allocate" in text or "bad_alloc" in text:
            raise ModelError(
                f"{src}: a prediction of {len(rows)} rows needs more than {PROBE_MEMORY_BYTES >> 20} MiB "
                "(a cmcan model needs a few kB a row): refused"
            ) from None
        raise ModelError(f"{src}: the model does not run: {type(exc).__name__}: {_first_line(text)}") from None
    finally:
        timer.cancel()


def _first_line(text: str) -> str:
    return text.strip().splitlines()[0][:300] if text.strip() else ""


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
    budget_s: float = PROBE_BUDGET_S,
) -> GrayBoxModel:
    """A model checked and probed within bounds (see the module's docstring): at most the file's
    bounded read, a session without constant folding and ``budget_s`` of probing."""
    return GrayBoxModel(path, expected_inputs, motor_disp_cc, quantity, oil, budget_s)


def default_model_path() -> Path:
    return Path(__file__).resolve().parent / "default.onnx"
