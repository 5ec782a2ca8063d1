"""Runtime wrapper of the exported encoder: numpy + onnxruntime only (no torch).

``OnnxEncoder(path).reconstruct(erp_a, erp_b, c2w_a, c2w_b)`` validates the
inputs, resamples both panoramas to the model's size, computes the
pose-dependent graph inputs (:mod:`rasterizer.sweep`), runs the graph and
wraps the outputs in :class:`rasterizer.gaussians.Gaussians`.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import onnxruntime as ort

from rasterizer.colour_fit import COLOUR_FIT_STRENGTH, check_colour_fit, fit_reference_colours
from rasterizer.gaussians import Gaussians
from rasterizer.geometry import PoseError, as_c2w
from rasterizer.rig import check_rig_cap, patch_rig, resolve_rig_cap, rig_summary
from rasterizer.shell import environment_shell, shell_radius
from rasterizer.sweep import (
    FAR_PER_BASELINE,
    INPUT_NAMES,
    MIN_BASELINE,
    NEAR_PER_BASELINE,
    OUTPUT_NAMES,
    WARP_GRIDS_RANK,
    SweepRangeError,
    baseline,
    check_scene_scale,
    default_near_far,
    grids_for_mode,
    sweep_inputs,
)
from rasterizer.view_colour import DEFAULT_SH_DEGREE, check_sh_degree, fit_view_colour
from rasterizer.yin_yang import resize_erp

from .model_files import sha256_file

KNOWN_OPTIONS = ("min_opacity", "sh_degree", "rig_cap_deg", "colour_fit")
#: metadata of every exported encoder that sizes its inputs and outputs (positive integers), in this order
LAYOUT_METADATA = ("input_height", "input_width", "num_planes", "feature_height", "feature_width",
                   "gaussian_grid_height", "gaussian_grid_width")
#: metadata holding JSON text (decoded by :attr:`OnnxEncoder.metadata`)
JSON_METADATA = ("settings", "inputs")


def _positive_int(props: dict, key: str) -> int:
    """``props[key]`` as a positive int; a ValueError naming the key when it is absent or another value."""
    if key not in props:
        raise ValueError(f"it has no {key!r} (every omnisplat export records {', '.join(LAYOUT_METADATA)})")
    text = props[key].strip()
    if not text.isdecimal() or int(text) < 1:
        raise ValueError(f"its {key} is {props[key][:40]!r}, not a positive integer")
    return int(text)


def _json(props: dict, key: str) -> None:
    """A ValueError naming ``key`` when ``props[key]`` is present but not JSON text."""
    try:
        json.loads(props.get(key, "null"))
    except ValueError as exc:
        raise ValueError(f"its {key} is not JSON ({exc})") from None


def _choice(props: dict, key: str, allowed: tuple[str, ...], default: str) -> str:
    """``props[key]`` (``default`` when absent), one of ``allowed``; else a ValueError naming the key."""
    value = props.get(key, default)
    if value not in allowed:
        raise ValueError(f"its {key} is {value[:40]!r}; this runtime reads {' or '.join(map(repr, allowed))}")
    return value


class EncoderInputError(ValueError):
    """An input the encoder cannot use (bad image, pose or option); the message says why."""


@dataclass
class Reconstruction:
    """Result of :meth:`OnnxEncoder.reconstruct`.

    gaussians: world-space Gaussians of both views (SH degree ``info["sh_degree"]``; the shell's band
    is zero): the pixel-aligned ones in [view][grid][row][col] order, then the ``shell`` Gaussians of
    :mod:`rasterizer.shell`.
    timings: seconds per stage (resample, sweep_inputs, onnx, gaussians, total).
    info: near, far, baseline, counts, model name/version/sha256.
    range_maps, confidence: (2, G, Hg, Wg) per view and grid (Yin, Yang or ERP),
    range in scene units along each pixel ray, confidence in [0, 1].
    matches: (2, G, Hg, Wg, 5) each pixel's match in the other view (``export.matches``;
    channels named in :mod:`rasterizer.edit.correspondences`), None for models built before it.
    """

    gaussians: Gaussians
    timings: dict[str, float]
    info: dict
    range_maps: np.ndarray
    confidence: np.ndarray = field(repr=False)
    matches: np.ndarray | None = field(default=None, repr=False)
    shell: int = 0  # the last ``shell`` Gaussians are the environment shell (rasterizer.shell)


def _as_image(img, name: str) -> np.ndarray:
    """Validated (H, W, 3) RGB panorama, uint8 or float in [0, 1], returned without a copy.

    Conversion to float32 waits for :meth:`OnnxEncoder._to_chw`, after the resample to the model's
    size, so a large input (5760x2880) never exists as a full-size float copy.
    """
    arr = np.asarray(img)
    if arr.ndim != 3 or arr.shape[2] != 3:
        raise EncoderInputError(f"{name} must be an (H, W, 3) RGB array, got shape {arr.shape}")
    h, w = arr.shape[:2]
    if h < 2 or w != 2 * h:
        raise EncoderInputError(f"{name} must be an equirectangular panorama with width = 2 x height, got {w}x{h}")
    if arr.dtype == np.uint8:
        return arr
    if not np.issubdtype(arr.dtype, np.floating):
        raise EncoderInputError(f"{name} must be uint8 or float in [0, 1], got dtype {arr.dtype}")
    if not np.all(np.isfinite(arr)):
        raise EncoderInputError(f"{name} contains NaN or Inf")
    lo, hi = float(arr.min()), float(arr.max())
    if lo < -1e-3 or hi > 1.0 + 1e-3:
        raise EncoderInputError(f"{name} float values must lie in [0, 1], got [{lo:.3g}, {hi:.3g}]")
    return arr


def unit_image_at_size(img: np.ndarray, height: int, width: int) -> np.ndarray:
    """(height, width, 3) float32 in [0, 1] of an (H, W, 3) uint8 or float-in-[0, 1] panorama.

    Resampled first (:func:`rasterizer.yin_yang.resize_erp` converts in row blocks, so a large upload
    never exists as a full-size float copy), then scaled (uint8) or clipped (float); the caller's array
    is never modified.
    """
    if img.shape[:2] != (height, width):
        out = resize_erp(img, height, width)
    else:
        out = img.astype(np.float32)
    if img.dtype == np.uint8:
        out /= np.float32(255.0)
    else:
        np.clip(out, 0.0, 1.0, out=out)
    return out


#: cameras whose midpoint lies farther than this many baselines from the origin are moved
#: next to it for the float32 graph (dev scenes, near the origin, are untouched)
RECENTRE_BEYOND_BASELINES = 10.0


def recentring_offset(c2w_a: np.ndarray, c2w_b: np.ndarray) -> np.ndarray:
    """float64 offset subtracted from both camera centres before the graph (zeros when not needed)."""
    mid = 0.5 * (c2w_a[:3, 3] + c2w_b[:3, 3])
    if np.linalg.norm(mid) > RECENTRE_BEYOND_BASELINES * baseline(c2w_a, c2w_b):
        return mid
    return np.zeros(3)


class OnnxEncoder:
    """onnxruntime session of an exported encoder (CPU, explicit threading).

    ``threads`` intra-op threads, one inter-op thread, sequential execution,
    spinning off (the service shares the CPU with rendering).
    """

    def __init__(self, model_path, *, threads: int = 2) -> None:
        self.path = Path(model_path)
        if not self.path.is_file():
            raise FileNotFoundError(f"encoder model not found: {self.path}")
        so = ort.SessionOptions()
        so.intra_op_num_threads = int(threads)
        so.inter_op_num_threads = 1
        so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        so.enable_mem_pattern = True  # static shapes: one planned arena block per run
        so.enable_cpu_mem_arena = True  # reused within a run; shrunk after it (run options below)
        so.add_session_config_entry("session.intra_op.allow_spinning", "0")
        so.add_session_config_entry("session.inter_op.allow_spinning", "0")
        self.session = ort.InferenceSession(str(self.path), so, providers=["CPUExecutionProvider"])
        # give the arena's blocks back after each run: the server then holds about 0.3 GB less between requests
        self.run_options = ort.RunOptions()
        self.run_options.add_run_config_entry("memory.enable_memory_arena_shrinkage", "cpu:0")
        props = dict(self.session.get_modelmeta().custom_metadata_map)
        names = tuple(i.name for i in self.session.get_inputs())
        have = {o.name for o in self.session.get_outputs()}
        self.output_names = [n for n in OUTPUT_NAMES if n in have]  # older models lack ``matches``
        if names != INPUT_NAMES:
            raise ValueError(f"{self.path} is not an omnisplat encoder (inputs {names})")
        rank = len(self.session.get_inputs()[INPUT_NAMES.index("warp_grids")].shape)
        if rank != WARP_GRIDS_RANK:
            raise ValueError(f"{self.path} was built by an older exporter (its warp_grids input has {rank} dimensions, "
                             f"this runtime feeds {WARP_GRIDS_RANK}): rebuild it with `omnisplat export`")
        spacing = props.get("candidate_spacing", "inverse")
        if spacing != "inverse":  # its graph would read this runtime's candidates at the wrong ranges
            raise ValueError(f"{self.path} expects depth candidates spaced by {spacing!r}; this runtime feeds them "
                             "uniform in inverse range: rebuild it with `omnisplat export`")
        self._meta = {**props, "sha256": sha256_file(self.path), "path": str(self.path), "threads": int(threads)}
        try:
            for key in JSON_METADATA:  # decoded by ``metadata`` on every read: a broken one would fail each
                _json(props, key)
            self.height, self.width, self.num_planes, *feature, grid_h, grid_w = (
                _positive_int(props, key) for key in LAYOUT_METADATA)
            self.erp_encoder = _choice(props, "erp_encoder", ("false", "true"), "false") == "true"
            self.grids = tuple(_choice(props, "grids", (",".join(grids_for_mode(self.erp_encoder)),),
                                       ",".join(grids_for_mode(self.erp_encoder))).split(","))
            # default sweep range per unit baseline (models before 0.2 stored the same numbers as
            # near_default / far_default in metres for the 1 m design baseline)
            self.near_per_baseline = float(props.get("near_per_baseline", props.get("near_default", NEAR_PER_BASELINE)))
            self.far_per_baseline = float(props.get("far_per_baseline", props.get("far_default", FAR_PER_BASELINE)))
            if not 0 < self.near_per_baseline < self.far_per_baseline < np.inf:
                raise ValueError(f"its sweep range per baseline must satisfy 0 < near < far < inf, got "
                                 f"near {self.near_per_baseline:g}, far {self.far_per_baseline:g}")
        except (ValueError, TypeError) as exc:
            raise ValueError(f"{self.path}: unusable omnisplat metadata: {exc}: rebuild it with `omnisplat export`"
                             ) from None
        self.feature_size = (feature[0], feature[1])
        #: (rows, columns) of one Gaussian grid (Yin, Yang or ERP): one Gaussian per pixel
        self.grid_size = (grid_h, grid_w)
        self._check_graph()

    def _check_graph(self) -> None:
        """A ValueError unless the graph takes exactly the arrays this runtime feeds it for the metadata's sizes
        (the inputs :func:`rasterizer.sweep.sweep_inputs` builds, the panoramas at ``input_height`` x
        ``input_width``) and gives every output :meth:`reconstruct` reads. A model whose metadata disagrees with its
        graph would otherwise load, then fail each reconstruction (and the warm-up) inside onnxruntime."""
        missing = [n for n in OUTPUT_NAMES if n not in self.output_names and n != "matches"]
        if missing:
            raise ValueError(f"{self.path} is not an omnisplat encoder (it has no output {', '.join(missing)})")
        c2w_b = np.eye(4)
        c2w_b[0, 3] = 1.0
        feeds = sweep_inputs(np.eye(4), c2w_b, near=1.0, far=10.0, num_planes=self.num_planes,
                             feature_size=self.feature_size, erp_encoder=self.erp_encoder)
        expected = {"erp_a": (1, 3, self.height, self.width), "erp_b": (1, 3, self.height, self.width),
                    **{name: array.shape for name, array in feeds.items()}}
        expected_out = {"range_maps": (2, len(self.grids), *self.grid_size)}
        ports = [*self.session.get_inputs(), *(o for o in self.session.get_outputs() if o.name in expected_out)]
        for port in ports:
            want = expected.get(port.name, expected_out.get(port.name))
            got = tuple(port.shape)
            if len(got) != len(want) or any(isinstance(g, int) and g != w for g, w in zip(got, want)):
                raise ValueError(f"{self.path}: its {port.name} has shape {list(got)}, but its metadata "
                                 f"(input {self.height}x{self.width}, {self.num_planes} planes, features "
                                 f"{self.feature_size[0]}x{self.feature_size[1]}, grids {','.join(self.grids)} of "
                                 f"{self.grid_size[0]}x{self.grid_size[1]}) make it {list(want)}: "
                                 "rebuild it with `omnisplat export`")

    def _to_chw(self, img: np.ndarray) -> np.ndarray:
        """(H, W, 3) uint8 or float in [0, 1] (:func:`_as_image`) -> (1, 3, height, width) float32 in [0, 1]
        (:func:`unit_image_at_size`)."""
        out = unit_image_at_size(img, self.height, self.width)
        return np.ascontiguousarray(out.transpose(2, 0, 1))[None]

    @property
    def metadata(self) -> dict:
        """metadata_props of the model (strings; JSON fields decoded) plus sha256 and path."""
        out = dict(self._meta)
        for key in ("settings", "inputs"):
            if key in out:
                out[key] = json.loads(out[key])
        return out

    def reconstruct(self, erp_a, erp_b, c2w_a, c2w_b, *, near: float | None = None,
                    far: float | None = None, **options) -> Reconstruction:
        """Gaussians of two posed ERP panoramas (see the module docstring).

        erp_a, erp_b: (H, W, 3) uint8 or float in [0, 1], W = 2H, any size
        (the two may differ). c2w_a, c2w_b: 4x4 (or 3x4) OpenCV camera-to-world.
        near, far: sweep range in scene units (default proportional to the
        baseline b: the model's ``near_per_baseline`` and ``far_per_baseline``, :func:`rasterizer.sweep.default_near_far`,
        so a globally scaled scene gives the same result). options: ``min_opacity``
        drops Gaussians below that opacity; ``sh_degree`` 1 (default) fits view-dependent colour so
        that each reference sees its own image (:mod:`rasterizer.view_colour`), 0 keeps one colour
        per Gaussian; ``rig_cap_deg`` > 0 re-colours each reference's pixels within that many degrees of
        its nadir, where tripod captures show the rig, from the other reference (:mod:`rasterizer.rig`);
        absent or None: ``AUTO_RIG_CAP_DEG`` where both references show a rig, else 0; ``colour_fit``: the
        strength of the closed-form colour-fit step (:mod:`rasterizer.colour_fit`; default
        ``COLOUR_FIT_STRENGTH``, 0 leaves the pixel colours as they are).
        Raises :class:`EncoderInputError`.
        """
        unknown = sorted(set(options) - set(KNOWN_OPTIONS))
        if unknown:
            raise EncoderInputError(f"unknown encoder option(s) {unknown}; known: {list(KNOWN_OPTIONS)}")
        try:
            sh_degree = check_sh_degree(options.get("sh_degree", DEFAULT_SH_DEGREE))
            rig_cap = check_rig_cap(options.get("rig_cap_deg"))
            colour_fit = check_colour_fit(options.get("colour_fit", COLOUR_FIT_STRENGTH))
        except ValueError as exc:
            raise EncoderInputError(str(exc)) from None
        t_start = time.perf_counter()
        timings: dict[str, float] = {}
        img_a, img_b = _as_image(erp_a, "erp_a"), _as_image(erp_b, "erp_b")
        try:
            pa, pb = as_c2w(c2w_a), as_c2w(c2w_b)
        except PoseError as exc:
            raise EncoderInputError(str(exc)) from None
        b = baseline(pa, pb)
        if b < MIN_BASELINE:
            raise EncoderInputError("the two camera centres coincide: depth cannot be triangulated "
                                    f"(baseline {b:.3g})")
        try:
            check_scene_scale(pa, pb, near, far)
        except SweepRangeError as exc:
            raise EncoderInputError(str(exc)) from None
        poses = np.stack([pa, pb])  # the caller's frame (the shell is built there)
        origin = recentring_offset(pa, pb)
        pa, pb = pa.copy(), pb.copy()
        pa[:3, 3] -= origin
        pb[:3, 3] -= origin
        n_def, f_def = default_near_far(pa, pb, near_ratio=self.near_per_baseline, far_ratio=self.far_per_baseline)
        automatic = [name for name, value in (("near", near), ("far", far)) if value is None]
        near = n_def if near is None else float(near)
        far = f_def if far is None else float(far)
        if not (np.isfinite(near) and np.isfinite(far) and 0 < near < far):
            which = f" ({' and '.join(automatic)}: automatic for this baseline, {b:.3g})" if automatic else ""
            raise EncoderInputError(f"need 0 < near < far, finite; got near={near:g}, far={far:g}{which}")

        t = time.perf_counter()
        chw = [self._to_chw(im) for im in (img_a, img_b)]
        timings["resample"] = time.perf_counter() - t
        rig_info = rig_summary(*(c[0].transpose(1, 2, 0) for c in chw))  # the images the model sees
        rig_cap = resolve_rig_cap(rig_cap, rig_info["detected"])

        t = time.perf_counter()
        feeds = sweep_inputs(pa, pb, near=near, far=far, num_planes=self.num_planes,
                             feature_size=self.feature_size, erp_encoder=self.erp_encoder)
        feeds["erp_a"], feeds["erp_b"] = chw
        timings["sweep_inputs"] = time.perf_counter() - t

        t = time.perf_counter()
        out = dict(zip(self.output_names, self.session.run(self.output_names, {k: feeds[k] for k in INPUT_NAMES},
                                                           self.run_options)))
        timings["onnx"] = time.perf_counter() - t

        t = time.perf_counter()
        arrays = [out[k] for k in ("means", "scales", "quats", "opacities", "sh_dc")]
        arrays[4] = arrays[4][:, None, :]
        if origin.any():  # back to the caller's frame, offset added in float64
            arrays[0] = (arrays[0].astype(np.float64) + origin).astype(np.float32)
        gaussians, rig = patch_rig(Gaussians(*arrays), out["range_maps"], poses, self.grids, rig_cap)
        radius = shell_radius(out["range_maps"])
        shell = environment_shell(gaussians, out["range_maps"], poses, self.grids, radius)
        t_fit = time.perf_counter()
        gaussians = fit_reference_colours(gaussians, out["confidence"], poses, self.grids, strength=colour_fit)
        timings["colour_fit"] = time.perf_counter() - t_fit  # part of "gaussians"
        if sh_degree == 1:  # the shell keeps one colour (concatenate pads its SH with zeros)
            gaussians = fit_view_colour(gaussians, out["range_maps"], poses, self.grids, hidden=rig)
        min_opacity = float(options.get("min_opacity", 0.0))
        if min_opacity > 0:
            gaussians = gaussians.subset(gaussians.opacities >= min_opacity)
        gaussians = Gaussians.concatenate([gaussians, shell])
        timings["gaussians"] = time.perf_counter() - t
        timings["total"] = time.perf_counter() - t_start
        info = {
            "near": near, "far": far, "baseline": b, "num_planes": self.num_planes,
            "num_gaussians": len(gaussians), "num_gaussians_raw": int(out["means"].shape[0]),
            "num_gaussians_shell": len(shell), "shell_radius": radius, "sh_degree": sh_degree, "rig_cap_deg": rig_cap,
            "colour_fit": colour_fit,
            "rig": rig_info,
            "grids": self._meta.get("grids"), "input_size": [self.height, self.width],
            "mean_confidence": float(out["confidence"].mean()),
            "model": {k: self._meta.get(k) for k in ("name", "version", "sha256")},
        }
        return Reconstruction(gaussians, timings, info, out["range_maps"], out["confidence"], out.get("matches"),
                              len(shell))
