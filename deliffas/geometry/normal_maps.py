"""Per-frame UV-space normal maps as a gather through a precomputed texel table.

Conventions (docs/conventions.md): world-space unit normals, channel-first (3, S, S), values in
[-1, 1] (not (n + 1) / 2), 0 on texels that are not ``valid`` in the texel table. The temporal
window stacks frames f, f-1, ..., f-T along channels (oldest last), clamped at the first frame.

The texel -> (face, barycentrics) table depends only on the atlas, so it is turned once into
per-texel (vertex index, weight) triples; each frame is then one gather and a weighted sum.

On CPU, ``NormalMapGather.apply`` runs that gather as one fused C loop (interpolate, normalise,
write channel-first, zeros on invalid texels; AVX2 gathers where the CPU has them). The loop is
compiled with the system C compiler (``$CC``, else ``cc`` / ``gcc`` / ``clang``) the first time
it is needed in a process, into a temporary directory that is deleted once the library is loaded,
and called through ``ctypes``. Without a compiler (or with ``DELIFFAS_NATIVE=0``) ``apply`` falls
back to the sparse-matrix product, with the reason logged once; ``fused_kernel_status`` reports
which path is in use and how long the build took.

Arrays (``deliffas.geometry.arrays``): ``normal_maps``, ``NormalMapGather.apply``, ``temporal_window``
and ``rasterize_normal_map_naive`` return numpy for numpy input and a tensor on the input's device
for a tensor; the maps' dtype is the ``dtype`` argument, else the input's. ``NormalMapGather`` holds
its tables as CPU tensors (``to(device)`` moves them).
"""

from __future__ import annotations

import ctypes
import warnings
from dataclasses import dataclass
from typing import Literal, Union

import numpy as np
import torch
from jaxtyping import Float, Integer, Real, Shaped
from torch import Tensor

from deliffas.checks import check_shape
from deliffas.geometry.arrays import ArrayLike, is_numpy, to_numpy, to_torch
from deliffas.geometry.atlas import TexelTable, UVAtlas, uv_texel_table
from deliffas.native import LazyLibrary

__all__ = [
    "NormalMapGather",
    "FusedKernelStatus",
    "fused_kernel_status",
    "normal_maps",
    "temporal_window",
    "rasterize_normal_map_naive",
    "NORMAL_EPS",
]


NORMAL_EPS = 1e-8
"""Interpolated normals shorter than this are written as 0 (cannot be normalised)."""


_CFLAGS = ("-fno-math-errno", "-fno-trapping-math", "-ffp-contract=off")
"""No -ffast-math: results stay IEEE (no reciprocal-sqrt approximations, no reassociation)."""


@dataclass(frozen=True)
class FusedKernelStatus:
    """Whether ``NormalMapGather.apply`` can use the fused C kernel in this process.

    Attributes:
        available: the kernel is built and loaded.
        reason: why it is not available ("" when it is).
        build_seconds: wall time of the compiler run(s) and the library load (0 when not built).
        command: the compiler command line that built it ("" when not built).
        avx2: the loaded kernel has the AVX2 path (else the scalar loop only).
    """

    available: bool
    reason: str = ""
    build_seconds: float = 0.0
    command: str = ""
    avx2: bool = False


_KERNEL = LazyLibrary("normal_maps", "normal_maps.c", _CFLAGS,  # signatures: normal_maps.h
                      fallback="the sparse product for normal maps, slower")


def fused_kernel_status() -> FusedKernelStatus:
    """Build the fused kernel if this process has not tried yet, and report whether it is in use."""
    built = _KERNEL.load()
    if built.lib is None:
        return FusedKernelStatus(False, built.reason)
    return FusedKernelStatus(True, "", built.build_seconds, built.command, bool(built.lib.deliffas_normal_maps_avx2()))


@dataclass(frozen=True)
class NormalMapGather:
    """Per-texel vertex indices and barycentric weights of one atlas at side S.

    The same weights are held as flat (S*S, 3) index / weight arrays (the definition, used by
    ``method="gather"``), as a sparse CSR matrix (S*S, V) with three entries per valid texel, so
    that a frame's map is one sparse-dense product (``method="sparse"``, the fallback off CPU or
    without a C compiler: about 2-4x faster than the dense gather on CPU at S = 1024), and, built
    at the first fused ``apply``, as planar (3, S*S) int32 vertex ids (-1 on invalid texels) and
    float32 weights for the fused C kernel (``method="fused"``, the default on CPU).

    Attributes:
        size: S.
        vert_index: (S*S, 3) int64, vertices of the texel's face (0 where the texel is not valid).
        weights: (S*S, 3) float32, barycentrics (0 where the texel is not valid, so the
            interpolated normal is 0 there).
        matrix: (S*S, V) float32 sparse CSR, row t = the weights of texel t on its three vertices.
    """

    size: int
    vert_index: Integer[Tensor, "S2 3"]
    weights: Float[Tensor, "S2 3"]
    matrix: Tensor

    @classmethod
    def from_table(cls, table: TexelTable, faces: Integer[ArrayLike, "F 3"], num_verts: int | None = None) -> "NormalMapGather":
        """Flatten a texel table against the mesh's faces.

        Args:
            table: TexelTable of side S (``face``/``bary`` of every texel).
            faces: (F, 3) int, the same faces the atlas was built for.
            num_verts: V (default: max vertex index in ``faces`` + 1; normals of further, unused
                vertices are ignored by ``apply``).
        """
        check_shape("faces", faces, "F 3")
        faces_np = to_numpy(faces, np.int64)
        if faces_np.min(initial=0) < 0:
            raise ValueError(f"faces: vertex indices must be >= 0, got {faces_np.min()}")
        face = table.face.reshape(-1)
        if face.max(initial=-1) >= len(faces_np):
            raise ValueError(f"texel table refers to face {face.max()} but faces has {len(faces_np)} rows")
        num_verts = int(num_verts if num_verts is not None else faces_np.max(initial=-1) + 1)
        valid = table.valid.reshape(-1) & (face >= 0)
        vert_index = np.where(valid[:, None], faces_np[np.maximum(face, 0)], 0).astype(np.int64)
        weights = np.where(valid[:, None], table.bary.reshape(-1, 3), 0.0).astype(np.float32)
        rows = np.repeat(np.flatnonzero(valid), 3)
        cols = vert_index[valid].reshape(-1)
        vals = weights[valid].reshape(-1)
        S2 = table.size * table.size
        # duplicate (row, col) pairs cannot occur: a face has three distinct vertices
        crow = np.zeros(S2 + 1, np.int64)
        np.add.at(crow, rows + 1, 1)
        with warnings.catch_warnings():  # "sparse CSR support is in beta" (CPU and CUDA matmul are fine)
            warnings.simplefilter("ignore", UserWarning)
            matrix = torch.sparse_csr_tensor(
                torch.from_numpy(np.cumsum(crow)), torch.from_numpy(cols), torch.from_numpy(vals), size=(S2, num_verts)
            )
        return cls(table.size, torch.from_numpy(vert_index), torch.from_numpy(weights), matrix)

    def to(self, device: Union[str, torch.device]) -> "NormalMapGather":
        """The same gather with its tensors on ``device``."""
        return NormalMapGather(self.size, self.vert_index.to(device), self.weights.to(device), self.matrix.to(device))

    def _fused_tables(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(3, S*S) int32 vertex ids (row 0 is -1 on invalid texels) and (3, S*S) float32 weights, on CPU.

        Built once from ``vert_index`` / ``weights`` and kept. A texel counts as invalid when all
        its weights are 0 (``from_table`` zeroes them there; a valid texel's weights sum to 1);
        either way its normal is 0.
        """
        tables = self.__dict__.get("_fused")
        if tables is None:
            vi, w = self.vert_index.cpu(), self.weights.cpu().float()
            if vi.numel() and (int(vi.min()) < 0 or int(vi.max()) >= self.matrix.shape[1]):
                raise ValueError(f"vert_index: entries must be in [0, {self.matrix.shape[1]})")
            valid = (w != 0).any(1)
            vid = torch.where(valid[:, None], vi, 0).to(torch.int32).T.contiguous()
            vid[0].masked_fill_(~valid, -1)
            tables = (vid, w.T.contiguous())
            object.__setattr__(self, "_fused", tables)  # frozen dataclass: a cache, not a field
        return tables

    def apply(
        self, vertex_normals: Real[ArrayLike, "*B V 3"], dtype: torch.dtype | np.dtype | type | None = None,
        method: Literal["auto", "fused", "sparse", "gather"] = "auto",
    ) -> Float[ArrayLike, "*B 3 S S"]:
        """Normal maps of one or more frames.

        Args:
            vertex_normals: (..., V, 3) float, unit world-space vertex normals (torch or numpy).
            dtype: output dtype, torch or numpy (e.g. ``torch.float16`` / ``np.float16`` for
                storage); default: input dtype. Interpolation runs in the input dtype (float32 at least).
            method: "fused" (one C loop per frame, CPU only; see the module docstring), "sparse"
                (one sparse-dense product), "gather" (index + weighted sum), or "auto": fused on
                CPU when the kernel is available, else sparse. Same result within ~1e-7 (fused
                and gather agree to the last bit on most texels).

        Returns:
            (..., 3, S, S) barycentric interpolation of the three vertex normals of each valid
            texel's face, re-normalised; 0 where not valid. numpy for numpy input, else a tensor on
            the input's device.
        """
        check_shape("vertex_normals", vertex_normals, "* V 3")
        if method not in ("auto", "fused", "sparse", "gather"):
            raise ValueError(f"method: expected 'auto', 'fused', 'sparse' or 'gather', got {method!r}")
        out = self._apply(to_torch(vertex_normals), _torch_dtype(dtype), method)
        return to_numpy(out) if is_numpy(vertex_normals) else out

    def _apply(self, vn: torch.Tensor, dtype: torch.dtype | None, method: str) -> torch.Tensor:
        out_dtype = dtype or vn.dtype
        if not vn.dtype.is_floating_point or vn.dtype in (torch.float16, torch.bfloat16):
            vn = vn.float()
        lead = vn.shape[:-2]
        num_verts = vn.shape[-2]
        S = self.size
        cols = self.matrix.shape[1]  # vertices referenced by the faces (trailing unused ones are ignored)
        if num_verts < cols:
            raise ValueError(f"vertex_normals: expected at least V = {cols} vertices, got shape {tuple(vn.shape)}")
        if method in ("auto", "fused"):
            lib = None
            if vn.device.type == "cpu" and vn.dtype in (torch.float32, torch.float64):
                lib = _KERNEL.get()
            if lib is not None:
                return self._apply_fused(lib, vn, out_dtype).reshape(*lead, 3, S, S)
            if method == "fused":
                why = fused_kernel_status().reason if vn.device.type == "cpu" else f"input on {vn.device}"
                raise RuntimeError(f"method='fused' is not available: {why}")
            method = "sparse"
        vb = vn.reshape(-1, num_verts, 3)  # (B, V, 3)
        B = vb.shape[0]
        if method == "sparse":
            m = self.matrix.to(device=vn.device, dtype=vn.dtype)
            x = vb[:, :cols].permute(1, 0, 2).reshape(cols, B * 3)  # (V, B*3)
            n = (m @ x).view(S * S, B, 3).permute(1, 0, 2)  # (B, S*S, 3) strided view
        elif method == "gather":
            vi = self.vert_index.to(vn.device)
            w = self.weights.to(device=vn.device, dtype=vn.dtype)[:, :, None]  # (S*S, 3, 1)
            n = vb[:, vi[:, 0]] * w[:, 0] + vb[:, vi[:, 1]] * w[:, 1] + vb[:, vi[:, 2]] * w[:, 2]  # (B, S*S, 3)
        c = n.unbind(-1)  # 3 x (B, S*S) strided views
        sq = c[0] * c[0]
        sq.addcmul_(c[1], c[1]).addcmul_(c[2], c[2])  # (B, S*S) squared lengths, no (B, S*S, 3) temporary
        inv = torch.where(sq > NORMAL_EPS**2, sq.rsqrt(), 0.0)
        out = torch.empty((B, 3, S * S), dtype=out_dtype, device=vn.device)
        for k in range(3):  # normalise straight into the channel-first output (+ cast)
            if out_dtype == n.dtype:
                torch.mul(c[k], inv, out=out[:, k])
            else:
                out[:, k] = c[k] * inv
        return out.reshape(*lead, 3, S, S)

    def _apply_fused(self, lib: ctypes.CDLL, vn: torch.Tensor, out_dtype: torch.dtype) -> torch.Tensor:
        """(B, 3, S*S) maps of float32 / float64 CPU normals (..., V, 3) through the C kernel."""
        vid, w = self._fused_tables()
        num_verts = vn.shape[-2]
        vb = vn.reshape(-1, num_verts, 3).contiguous()  # (B, V, 3)
        B, S2 = vb.shape[0], self.size * self.size
        out = torch.empty((B, 3, S2), dtype=vb.dtype)
        fn = lib.deliffas_normal_maps_f32 if vb.dtype == torch.float32 else lib.deliffas_normal_maps_f64
        # ctypes releases the GIL for the call; vb, vid, w and out are referenced until it returns
        fn(vb.data_ptr(), num_verts * 3, vid.data_ptr(), w.data_ptr(), out.data_ptr(), S2, B, NORMAL_EPS**2)
        return out if out_dtype == out.dtype else out.to(out_dtype)  # the cast of the eager paths


def _torch_dtype(dtype: torch.dtype | np.dtype | type | None) -> torch.dtype | None:
    """A torch dtype for a torch or numpy one (None stays None)."""
    if dtype is None or isinstance(dtype, torch.dtype):
        return dtype
    return torch.from_numpy(np.zeros(0, dtype)).dtype


def normal_maps(vertex_normals: Real[ArrayLike, "*B V 3"], faces: Integer[ArrayLike, "F 3"], table: TexelTable,
                dtype: torch.dtype | np.dtype | type | None = None) -> Float[ArrayLike, "*B 3 S S"]:
    """Normal maps (B, 3, S, S) of vertex normals (B, V, 3) through ``table``.

    One-shot convenience over ``NormalMapGather.from_table(table, faces).apply(...)``; build the
    gather once and reuse it when converting many frames. numpy for numpy input, else a tensor on
    the input's device.
    """
    check_shape("vertex_normals", vertex_normals, "* V 3")
    gather = NormalMapGather.from_table(table, faces, num_verts=vertex_normals.shape[-2])
    return gather.apply(vertex_normals, dtype=dtype)


def temporal_window(maps_per_frame: Shaped[ArrayLike, "F 3 S S"], rows: Integer[ArrayLike, "B"],
                    window: int) -> Shaped[ArrayLike, "B C S S"]:
    """Stack frames f, f-1, ..., f-T along channels, clamped at the first frame.

    Args:
        maps_per_frame: (F, 3, S, S) normal maps of consecutive frames (torch or numpy).
        rows: (B,) int, the row of ``maps_per_frame`` holding the current frame of each batch item
            (a position, not a capture frame number: row 0 is the first frame given).
        window: T, the number of previous frames (T = 2 in DELIFFAS: t, t-1, t-2).

    Returns:
        (B, 3 (T + 1), S, S), same kind as ``maps_per_frame``; channels [3k:3k+3] hold row
        max(r - k, 0).
    """
    sizes = check_shape("maps_per_frame", maps_per_frame, "F 3 S S")
    check_shape("rows", rows, "B")
    if window < 0:
        raise ValueError(f"temporal_window: window must be >= 0, got {window}")
    if isinstance(maps_per_frame, torch.Tensor):
        fi = to_torch(rows, torch.long, maps_per_frame.device)
        if fi.numel() and (fi.min() < 0 or fi.max() >= sizes["F"]):
            raise ValueError(f"rows: must be in [0, {sizes['F']}), got [{int(fi.min())}, {int(fi.max())}]")
        idx = (fi[:, None] - torch.arange(window + 1, device=fi.device)).clamp_min(0)  # (B, T+1)
        out = maps_per_frame[idx]  # (B, T+1, 3, S, S)
    else:
        fi = to_numpy(rows, np.int64)
        if fi.size and (fi.min() < 0 or fi.max() >= sizes["F"]):
            raise ValueError(f"rows: must be in [0, {sizes['F']}), got [{fi.min()}, {fi.max()}]")
        idx = np.maximum(fi[:, None] - np.arange(window + 1), 0)
        out = np.asarray(maps_per_frame)[idx]
    S = sizes["S"]
    return out.reshape(len(fi), 3 * (window + 1), S, S)


def rasterize_normal_map_naive(
    vertex_normals: Real[ArrayLike, "B V 3"], faces: Integer[ArrayLike, "F 3"], atlas: UVAtlas, size: int, gutter: int = 2
) -> Float[ArrayLike, "B 3 S S"]:
    """Baseline for benchmarks: re-rasterise the atlas for every frame, then interpolate.

    Same result as ``NormalMapGather.apply`` but pays ``uv_texel_table`` per frame, as a
    renderer that draws the normal map in UV space each frame does.

    Args:
        vertex_normals: (B, V, 3) float unit normals.
        faces: (F, 3) int.
        atlas: UVAtlas of the mesh.
        size: S.
        gutter: dilation rings.

    Returns:
        (B, 3, S, S) float, numpy or torch as ``vertex_normals``.
    """
    check_shape("vertex_normals", vertex_normals, "B V 3")
    vn = to_torch(vertex_normals)
    frames = []
    for b in range(vn.shape[0]):  # per frame, by design of this baseline
        table = uv_texel_table(atlas, size, gutter)
        frames.append(NormalMapGather.from_table(table, faces, num_verts=vn.shape[1]).apply(vn[b]))
    out = torch.stack(frames)
    return to_numpy(out) if is_numpy(vertex_normals) else out
