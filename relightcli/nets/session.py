"""The ONNX Runtime session every model family builds on (after rembg's BaseSession).

`ModelSession` owns what is common: finding the model through the manifest, the sha256 check,
session creation (providers, threads), and the check that the loaded graph has the I/O contract
the manifest promises. The family classes (`GeometryNet`, `DelightNet`, ...) only convert
layouts, pad, run, and crop.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from relightcli.errors import MissingDependencyError, UsageError
from relightcli.nets.manifest import MODELS_FIX, ModelEntry, TensorContract, model_entry, sha256_file

CUDA_PROVIDER = "CUDAExecutionProvider"
CPU_PROVIDER = "CPUExecutionProvider"
# ONNX Runtime type strings for the dtypes a manifest may name.
ORT_DTYPES = {"float32": "tensor(float)", "float16": "tensor(float16)", "int64": "tensor(int64)"}


# A session built for the one input shape it runs on (ONNX Runtime's free dimension overrides:
# N, H, W fixed) plans its shape arithmetic and buffers once:
# the body refinement net at 512 ran 0.44 -> 0.35 s on one thread and 0.28 -> 0.18 s on two,
# the other nets 3-10% faster (back to back, 5 runs each, `ModelSession` alone); the outputs
# differ from a free session's by float rounding (2e-7 of the refined shading), so every shape
# runs on its own fixed session: the same bytes whichever shapes a process was prepared for
FREE_DIMS = ("N", "H", "W")

# Session log severity: errors only. Warnings (graph optimisation notes) mean nothing to a user
# and come in colour codes on stderr, into the batch log.
ORT_LOG_ERRORS = 3


def import_onnxruntime():
    """onnxruntime with its telemetry off. On import it writes a device id under
    ~/.cache/Microsoft and warns in colour when it cannot (a read-only container, a --user
    without a home); ORT_DISABLE_TELEMETRY, set before the first import, stops both (a caller's
    setting wins). The only place relightcli imports onnxruntime."""
    os.environ.setdefault("ORT_DISABLE_TELEMETRY", "1")
    try:
        import onnxruntime
    except ImportError as exc:
        raise MissingDependencyError("onnxruntime is not installed", fix="pip install onnxruntime") from exc
    onnxruntime.disable_telemetry_events()
    return onnxruntime


def select_providers(available: list[str] | None = None) -> list[str]:
    """CUDA first when this onnxruntime build has it, then CPU (always last, the fallback)."""
    if available is None:
        available = import_onnxruntime().get_available_providers()
    return ([CUDA_PROVIDER] if CUDA_PROVIDER in available else []) + [CPU_PROVIDER]


class ModelSession:
    """One ONNX model from the manifest, verified and loaded.

    Subclasses set `model_name` (the manifest key) and `input_names` / `output_names` (what
    their pre/post-processing relies on); the manifest must promise at least those.
    """

    model_name: str = ""
    input_names: tuple[str, ...] = ()
    output_names: tuple[str, ...] = ()

    def __init__(
        self,
        name: str | None = None,
        *,
        models_dir: str | Path | None = None,
        threads: int | None = None,
        providers: list[str] | None = None,
        verify_sha256: bool = True,
        run_size: int | None = None,
    ):
        """threads: intra-op threads (None: ONNX Runtime's default, all cores).
        verify_sha256: hash the file against the manifest (about 1 s per GB).
        run_size: the side of the square inputs (padded) it will run on, one at a time: the
        session for that shape is built now, any other shape's the first time one comes
        (each input shape runs on a session built for it: FREE_DIMS)."""
        self.name = name or self.model_name
        if not self.name:
            raise UsageError("no model name given", fix="pass name= or use a model family class")
        if threads is not None and (not isinstance(threads, int) or threads < 1):
            raise UsageError(f"threads must be a positive integer, got {threads!r}", fix="use --threads 1 or more")
        self.entry: ModelEntry = model_entry(self.name, models_dir)
        self.path = self.entry.path
        self.trained_resolution = self.entry.trained_resolution
        self.threads, self._providers, self._shaped = threads, providers, {}
        self._check_family_contract()
        self._check_file(verify_sha256)
        # the first input with free dimensions: its (dim, size) pairs key the sessions
        self._keyed = next((t for t in self.entry.inputs if set(t.shape) & set(FREE_DIMS)), None)
        planned = {"N": 1, "H": run_size, "W": run_size}
        shape = tuple((d, planned[d]) for d in FREE_DIMS if d in self._keyed.shape) \
            if run_size and self._keyed is not None else None
        self.session = self._create_session(threads, providers, shape)
        if shape is not None:
            self._shaped[shape] = self.session
        self._check_graph_contract()

    @property
    def multiple(self) -> int:
        return self.entry.multiple

    @property
    def providers(self) -> list[str]:
        return self.session.get_providers()

    def run(self, feeds: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """Run on NCHW float32 arrays keyed by input name; returns every output by name."""
        expected = {t.name: t for t in self.entry.inputs}
        if set(feeds) != set(expected):
            raise ValueError(f"{self.name}: feeds {sorted(feeds)} != model inputs {sorted(expected)}")
        for name, array in feeds.items():
            _check_array(self.name, expected[name], array, self.multiple)
        arrays = {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in feeds.items()}
        names = [t.name for t in self.entry.outputs]
        return dict(zip(names, self._session_for(arrays).run(names, arrays)))

    def _session_for(self, arrays: dict):
        """The session built for these inputs' (N, H, W), built now if none is."""
        if self._keyed is None:
            return self.session
        promised, array = self._keyed, arrays[self._keyed.name]
        shape = tuple((d, int(array.shape[promised.shape.index(d)])) for d in FREE_DIMS if d in promised.shape)
        if shape not in self._shaped:
            self._shaped[shape] = self._create_session(self.threads, self._providers, shape)
        return self._shaped[shape]

    # -- loading and checks -------------------------------------------------------------------

    def _contract_error(self, what: str) -> MissingDependencyError:
        return MissingDependencyError(f"model {self.name!r} does not match its I/O contract: {what}",
                                      path=self.path, fix=MODELS_FIX)

    def _check_family_contract(self) -> None:
        promised_in = {t.name for t in self.entry.inputs}
        promised_out = {t.name for t in self.entry.outputs}
        if self.input_names and set(self.input_names) != promised_in:
            raise self._contract_error(f"manifest inputs {sorted(promised_in)}, "
                                       f"{type(self).__name__} needs {sorted(self.input_names)}")
        missing = set(self.output_names) - promised_out
        if missing:
            raise self._contract_error(f"manifest outputs lack {sorted(missing)}")

    def _check_file(self, verify_sha256: bool) -> None:
        if not self.path.is_file():
            raise MissingDependencyError(f"model file for {self.name!r} not found", path=self.path, fix=MODELS_FIX)
        if verify_sha256:
            actual = sha256_file(self.path)
            if actual != self.entry.sha256:
                raise MissingDependencyError(
                    f"model file is corrupt or outdated: sha256 {actual[:12]}... != manifest {self.entry.sha256[:12]}...",
                    path=self.path, fix=MODELS_FIX)

    def _create_session(self, threads: int | None, providers: list[str] | None, shape: tuple = ()):
        ort = import_onnxruntime()
        options = ort.SessionOptions()
        options.log_severity_level = ORT_LOG_ERRORS
        if threads is not None:
            options.intra_op_num_threads = threads
            options.inter_op_num_threads = 1
        options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        # No memory arena: it keeps every activation buffer of the largest run (measured: 1.19
        # GB peak for the four nets at a 256 crop with it, 0.52 GB without, same speed)
        options.enable_cpu_mem_arena = False
        # No spinning: ONNX Runtime's pool threads otherwise busy-wait after each run, taking
        # the second core from the numpy and ray-tracing work between the nets and from the
        # sessions being built ahead (Models.prefetch): one photo at 512, whole process, 5.66
        # -> 5.33 s on 2 cores (bench/whole_process.py --against), the nets' own runs as fast
        options.add_session_config_entry("session.intra_op.allow_spinning", "0")
        for dim, value in shape or ():  # (dim, size) pairs fixed: FREE_DIMS
            options.add_free_dimension_override_by_name(dim, int(value))
        try:
            return ort.InferenceSession(str(self.path), sess_options=options,
                                        providers=providers or select_providers())
        # ONNX Runtime raises its own exception types (Fail, InvalidProtobuf, InvalidGraph, ...),
        # all plain Exception subclasses; any of them means the file cannot be used.
        except Exception as exc:  # noqa: BLE001 - re-raised as a project error, not swallowed
            raise MissingDependencyError(f"ONNX Runtime cannot load the model: {exc}",
                                         path=self.path, fix=MODELS_FIX) from exc

    def _check_graph_contract(self) -> None:
        for kind, promised, actual in (
            ("input", self.entry.inputs, self.session.get_inputs()),
            ("output", self.entry.outputs, self.session.get_outputs()),
        ):
            by_name = {a.name: a for a in actual}
            if set(by_name) != {t.name for t in promised}:
                raise self._contract_error(f"graph {kind}s {sorted(by_name)}, manifest says "
                                           f"{sorted(t.name for t in promised)}")
            for t in promised:
                _check_node(self, kind, t, by_name[t.name])


def _check_node(owner: ModelSession, kind: str, promised: TensorContract, node) -> None:
    if len(node.shape) != promised.rank:
        raise owner._contract_error(f"{kind} {promised.name!r} has rank {len(node.shape)}, manifest says {promised.rank}")
    if ORT_DTYPES.get(promised.dtype) != node.type:
        raise owner._contract_error(f"{kind} {promised.name!r} is {node.type}, manifest says {promised.dtype}")
    for axis, (want, have) in enumerate(zip(promised.shape, node.shape)):
        if isinstance(want, int) and isinstance(have, int) and want != have:
            raise owner._contract_error(f"{kind} {promised.name!r} axis {axis} is {have}, manifest says {want}")


def _check_array(model: str, promised: TensorContract, array: np.ndarray, multiple: int) -> None:
    """Internal invariant: the family class fed a tensor of the promised rank, fixed dims and
    a spatial size divisible by the model's multiple."""
    if array.ndim != promised.rank:
        raise ValueError(f"{model}: input {promised.name!r} has rank {array.ndim}, expected {promised.rank}")
    for axis, (want, have) in enumerate(zip(promised.shape, array.shape)):
        if isinstance(want, int) and want != have:
            raise ValueError(f"{model}: input {promised.name!r} axis {axis} is {have}, expected {want}")
        if want in ("H", "W") and have % multiple:
            raise ValueError(f"{model}: input {promised.name!r} axis {axis} = {have} not divisible by {multiple}")
