"""Pose features: the OpenCL HOG against an independent NumPy implementation, crops, ONNX encoder."""
from __future__ import annotations

import numpy as np
import pytest

from ucad_cl.features import (HogExtractor, OnnxExtractor, box_mask, crop_square, l2_rows,
                              mask_bounds, square_windows)

pytestmark = pytest.mark.every_device      # tests/conftest.py: UCAD_TEST_DEVICES


# ----------------------------------------------------------------------------- NumPy reference

def hog_reference(crops: np.ndarray, *, cell: int, bins: int, signed: bool, eps: float,
                  clip: float, min_grad: float = 0.0, sil=None, sil_weight: float = 0.0
                  ) -> np.ndarray:
    """Float64 NumPy version of ucad_cl/kernels/features.cl (written from its header comment)."""
    x = crops.astype(np.int64)                                  # (B, S, S, 3), exact integers
    p = np.pad(x, ((0, 0), (1, 1), (1, 1), (0, 0)), mode="edge")
    gx = p[:, 1:-1, 2:] - p[:, 1:-1, :-2]
    gy = p[:, 2:, 1:-1] - p[:, :-2, 1:-1]
    m2 = gx ** 2 + gy ** 2
    c = np.argmax(m2, axis=-1)[..., None]                       # first maximum = lowest channel
    gx = np.take_along_axis(gx, c, -1)[..., 0]
    gy = np.take_along_axis(gy, c, -1)[..., 0]
    mag = np.maximum(np.sqrt(gx ** 2 + gy ** 2) / 255.0 - min_grad, 0.0)
    rng = 2 * np.pi if signed else np.pi
    t = np.mod(np.arctan2(gy, gx), rng)
    pos = t * bins / rng - 0.5
    b0 = np.floor(pos)
    frac = pos - b0
    b0 = b0.astype(int) % bins
    b1 = (b0 + 1) % bins
    B, S = crops.shape[:2]
    nc = S // cell
    cy, cx = np.meshgrid(np.arange(S) // cell, np.arange(S) // cell, indexing="ij")
    hist = np.zeros((B, nc, nc, bins))
    for b in range(B):
        np.add.at(hist[b], (cy, cx, b0[b]), mag[b] * (1 - frac[b]))
        np.add.at(hist[b], (cy, cx, b1[b]), mag[b] * frac[b])
    blocks = []
    for by in range(nc - 1):
        for bx in range(nc - 1):
            v = hist[:, by:by + 2, bx:bx + 2, :].reshape(B, -1)
            v = v / np.sqrt((v ** 2).sum(1, keepdims=True) + eps ** 2)
            v = np.minimum(v, clip)
            v = v / np.sqrt((v ** 2).sum(1, keepdims=True) + eps ** 2)
            blocks.append(v)
    h = np.concatenate(blocks, axis=1)
    nh = np.linalg.norm(h, axis=1, keepdims=True)
    h = np.divide(h, nh, out=np.zeros_like(h), where=nh > 0)
    if sil is None:
        return h
    s = sil.reshape(B, -1).astype(np.float64)
    ns = np.linalg.norm(s, axis=1, keepdims=True)
    s = np.divide(s, ns, out=np.zeros_like(s), where=ns > 0) * sil_weight
    f = np.concatenate([h, s], axis=1)
    nf = np.linalg.norm(f, axis=1, keepdims=True)
    return np.divide(f, nf, out=np.zeros_like(f), where=nf > 0)


def _random_crops(rng, B, S):
    """Smooth blobs plus noise and a few flat regions: every orientation and exact zeros."""
    yy, xx = np.mgrid[0:S, 0:S] / S
    imgs = np.empty((B, S, S, 3), np.uint8)
    for b in range(B):
        f = [np.sin(rng.uniform(2, 12) * xx + rng.uniform(0, 6)) *
             np.cos(rng.uniform(2, 12) * yy + rng.uniform(0, 6)) for _ in range(3)]
        img = 127.5 + 100 * np.stack(f, -1) + rng.normal(0, 8, (S, S, 3))
        img[: S // 4, : S // 4] = 77                            # flat: zero gradient
        imgs[b] = np.clip(img, 0, 255).astype(np.uint8)
    return imgs


@pytest.mark.parametrize("cfg", [
    dict(size=64, cell=8, bins=9, signed=False, eps=1.0),
    dict(size=48, cell=6, bins=12, signed=True, eps=0.01, min_grad=0.05),
    dict(size=32, cell=8, bins=18, signed=False, eps=1.0, silhouette=8, sil_weight=0.7),
])
def test_hog_kernel_matches_numpy_reference(runtime, cfg):
    rng = np.random.default_rng(1)
    ex = HogExtractor(**cfg, runtime=runtime)
    crops = _random_crops(rng, 5, ex.size)
    masks = (rng.random((5, ex.size, ex.size)) > 0.5).astype(np.float32)
    got = ex.describe(crops, masks)
    sil = None
    if ex.silhouette:
        import cv2
        sil = np.stack([cv2.resize(m, (ex.silhouette,) * 2, interpolation=cv2.INTER_AREA)
                        for m in masks])
    ref = hog_reference(crops, cell=ex.cell, bins=ex.bins, signed=ex.signed, eps=ex.eps,
                        clip=ex.clip, min_grad=ex.min_grad, sil=sil, sil_weight=ex.sil_weight)
    assert got.shape == (5, ex.dim) and got.dtype == np.float32
    np.testing.assert_allclose(got, ref, atol=1e-5, rtol=0)
    np.testing.assert_allclose(np.linalg.norm(got, axis=1), 1.0, atol=1e-5)


ATAN2_PROBE = """
kernel void atan2_probe(global const float *y, global const float *x, global float *out) {
    const int i = get_global_id(0);
    out[i] = same_bits_atan2(y[i], x[i]);
}
"""
ATAN2_COEFFS = ("0.0028662257", "-0.0161657367", "0.0429096138", "-0.0752896400",
                "0.1065626393", "-0.1420889944", "0.1999355085", "-0.3333314528")


def atan2_float32(y: np.ndarray, x: np.ndarray) -> np.ndarray:
    """features.cl's same_bits_atan2 replayed in NumPy float32 (each +, *, / rounded once, as
    IEEE and the kernel's FP_CONTRACT OFF with correctly rounded division require)."""
    f = np.float32
    pi = f("3.14159265358979")
    ax, ay = np.abs(x), np.abs(y)
    hi, lo = np.maximum(ax, ay), np.minimum(ax, ay)
    a = np.divide(lo, hi, out=np.zeros_like(lo), where=hi > 0)
    s = a * a
    q = np.full_like(a, f(ATAN2_COEFFS[0]))
    for c in ATAN2_COEFFS[1:]:
        q = q * s + f(c)
    r = a * (f(1.0) + q * s)
    r = np.where(ay > ax, f(0.5) * pi - r, r)
    r = np.where(x < 0, pi - r, r)
    return np.where(hi > 0, np.where(y < 0, -r, r), f(0.0)).astype(np.float32)


def test_orientation_is_the_same_bits_as_ieee_float_arithmetic(runtime):
    """The descriptor's orientation (``same_bits_atan2``) for every gradient the kernel can see
    (integer gx, gy in [-255, 255]): the same bits as the NumPy float32 replay, so any device with
    correctly rounded division gives these bits; within 4e-7 rad of float64 atan2."""
    import pyopencl as cl

    from ucad_cl.runtime import kernel_source

    g = np.arange(-255, 256, dtype=np.float32)
    y, x = (a.ravel().copy() for a in np.meshgrid(g, g, indexing="ij"))
    prg = runtime.build_source(kernel_source("features") + ATAN2_PROBE)
    mf = cl.mem_flags
    dy = cl.Buffer(runtime.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=y)
    dx = cl.Buffer(runtime.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=x)
    dout = cl.Buffer(runtime.ctx, mf.WRITE_ONLY, y.nbytes)
    prg.atan2_probe(runtime.queue, (y.size,), None, dy, dx, dout)
    got = np.empty_like(y)
    cl.enqueue_copy(runtime.queue, got, dout)
    ref = atan2_float32(y, x)
    assert np.array_equal(got.view(np.uint32), ref.view(np.uint32)), \
        f"{np.count_nonzero(got != ref)} of {y.size} orientations differ from the float32 replay"
    err = np.abs(got.astype(np.float64) - np.arctan2(y.astype(np.float64), x))
    assert err.max() <= 4e-7                # under 2 ulp of float at pi


def test_hog_is_deterministic_and_independent_of_work_group_size(runtime):
    crops = _random_crops(np.random.default_rng(2), 7, 64)
    a = HogExtractor(runtime=runtime).describe(crops)
    for lp, lc in ((64, None), (16, 16), (256, 64)):
        b = HogExtractor(local_pixels=lp, local_cells=lc, runtime=runtime).describe(crops)
        assert np.array_equal(a, b)


def test_hog_ignores_colour_inversion(runtime):
    """Unsigned orientations: a negative image has the same descriptor (paint colour robustness)."""
    crops = _random_crops(np.random.default_rng(3), 3, 64)
    a = HogExtractor(runtime=runtime).describe(crops)
    b = HogExtractor(runtime=runtime).describe(255 - crops)
    np.testing.assert_allclose(a, b, atol=1e-5)


def test_flat_image_gives_all_zero_row(runtime):
    crops = np.full((2, 64, 64, 3), 90, np.uint8)
    crops[1, 20:40, 10:50] = 200
    f = HogExtractor(runtime=runtime).describe(crops)
    assert np.all(f[0] == 0.0)
    assert abs(np.linalg.norm(f[1]) - 1.0) < 1e-5


def test_mask_bounds_and_windows_equal_a_per_mask_loop():
    """``mask_bounds`` (one reduction over the batch) against flatnonzero on each mask; an
    empty mask gives -1 and ``square_windows`` refuses it, naming the image."""
    rng = np.random.default_rng(11)
    masks = rng.random((9, 23, 31)) < 0.02
    masks[3] = False
    masks[4] = True
    masks[5] = False
    masks[5, 22, 30] = True                         # the last pixel alone
    masks[6] = False
    masks[6, 0, 0] = True                           # the first pixel alone
    got = mask_bounds(masks)
    assert got.dtype == np.int64 and got.shape == (9, 4)
    for b, m in enumerate(masks):
        rows, cols = np.flatnonzero(m.any(axis=1)), np.flatnonzero(m.any(axis=0))
        ref = [-1] * 4 if rows.size == 0 else [rows[0], cols[0], rows[-1], cols[-1]]
        assert got[b].tolist() == list(ref), b
    keep = np.array([b != 3 for b in range(9)])
    assert square_windows(masks[keep], 0.1) == square_windows(masks[keep], 0.1,
                                                              mask_bounds(masks[keep]))
    with pytest.raises(ValueError, match="image 3: mask is empty"):
        square_windows(masks, 0.1)


def test_crop_square_box_and_padding():
    img = np.zeros((1, 40, 60, 3), np.uint8)
    img[0, :, :, 0] = np.arange(60)[None, :]                     # column index in red
    img[0, :, :, 1] = np.arange(40)[:, None]                     # row index in green
    mask = np.zeros((1, 40, 60), bool)
    mask[0, 10:20, 30:50] = True                                 # h=10, w=20
    crops, m = crop_square(img, mask, size=24, pad=0.1)          # side ceil(20*1.2)=24: no resize
    # centre (15, 40); top = floor(15 - 12) = 3, left = floor(40 - 12) = 28
    assert np.array_equal(crops[0, :, 0, 1], np.arange(3, 27))
    assert np.array_equal(crops[0, 0, :, 0], np.minimum(np.arange(28, 52), 59))  # edge repeat
    assert m[0].sum() == 200


def test_crop_square_equals_index_gather_reference_at_every_border():
    """The crop is the square's pixels with indices clamped into the image (edge repeat), then
    INTER_AREA: compared with that definition written as a NumPy index gather, for boxes that
    touch each border, and pads that push the square past all four."""
    import cv2

    rng = np.random.default_rng(3)
    H, W = 37, 53
    images = rng.integers(0, 256, (12, H, W, 3), dtype=np.uint8)
    masks = np.zeros((12, H, W), bool)
    boxes = [(0, 5, 0, 7), (30, 37, 46, 53), (0, 37, 10, 12), (14, 16, 0, 53), (3, 9, 20, 31),
             (0, 37, 0, 53)] * 2
    for b, (y0, y1, x0, x1) in enumerate(boxes):
        masks[b, y0:y1, x0:x1] = True
    for pad in (0.0, 0.1, 0.8):
        crops, mcrops = crop_square(images, masks, 16, pad)
        for b in range(len(boxes)):
            rows = np.flatnonzero(masks[b].any(axis=1))
            cols = np.flatnonzero(masks[b].any(axis=0))
            side = int(np.ceil(max(rows[-1] - rows[0] + 1, cols[-1] - cols[0] + 1) * (1 + 2 * pad)))
            top = int(np.floor((rows[0] + rows[-1] + 1) / 2 - side / 2))
            left = int(np.floor((cols[0] + cols[-1] + 1) / 2 - side / 2))
            ri = np.clip(np.arange(top, top + side), 0, H - 1)
            ci = np.clip(np.arange(left, left + side), 0, W - 1)
            ref = cv2.resize(images[b][np.ix_(ri, ci)], (16, 16), interpolation=cv2.INTER_AREA)
            mref = cv2.resize(masks[b][np.ix_(ri, ci)].astype(np.float32), (16, 16),
                              interpolation=cv2.INTER_AREA)
            assert np.array_equal(crops[b], ref), (pad, b)
            assert np.array_equal(mcrops[b], mref), (pad, b)
    no_masks = crop_square(images, masks, 16, 0.1, with_masks=False)
    assert no_masks[1] is None and np.array_equal(no_masks[0], crop_square(images, masks, 16)[0])


def test_crop_errors_name_the_problem(runtime):
    img = np.zeros((2, 8, 8, 3), np.uint8)
    mask = np.zeros((2, 8, 8), bool)
    mask[0, 2:4, 2:4] = True
    with pytest.raises(ValueError, match="image 1: mask is empty"):
        crop_square(img, mask, 16)
    with pytest.raises(ValueError, match="uint8"):
        crop_square(img.astype(np.float32), mask, 16)
    with pytest.raises(ValueError, match="masks must be"):
        crop_square(img, mask[:, :4], 16)
    with pytest.raises(ValueError, match="box .* is empty"):
        box_mask((8, 8), (5, 5, 5, 7))
    with pytest.raises(ValueError, match="multiple of cell"):
        HogExtractor(size=60, cell=8, runtime=runtime)


def test_l2_rows_huge_and_zero():
    x = np.array([[3e300, 4e300], [0.0, 0.0], [3.0, 4.0]])
    y = l2_rows(x)
    np.testing.assert_allclose(y, [[0.6, 0.8], [0, 0], [0.6, 0.8]], rtol=1e-6)


# ----------------------------------------------------------------------------- ONNX encoder

def _tiny_encoder(path, tokens: bool):
    """Conv 3->4 channels, 8x8 kernel, stride 8 (a 'patch embedding'); optionally as tokens."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    rng = np.random.default_rng(0)
    w = rng.normal(size=(4, 3, 8, 8)).astype(np.float32)
    bias = rng.normal(size=4).astype(np.float32)
    nodes = [helper.make_node("Conv", ["x", "w", "b"], ["fmap"], strides=[8, 8])]
    out = "fmap"
    if tokens:                                   # (B, 4, h, w) -> (B, h*w, 4), CLS-like first token
        nodes += [helper.make_node("Reshape", ["fmap", "shape"], ["flat"]),
                  helper.make_node("Transpose", ["flat"], ["tok"], perm=[0, 2, 1])]
        out = "tok"
    inits = [numpy_helper.from_array(w, "w"), numpy_helper.from_array(bias, "b"),
             numpy_helper.from_array(np.array([0, 4, -1], np.int64), "shape")]
    graph = helper.make_graph(nodes, "tiny", [helper.make_tensor_value_info(
        "x", TensorProto.FLOAT, ["B", 3, 32, 32])],
        [helper.make_tensor_value_info(out, TensorProto.FLOAT, None)], initializer=inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)], ir_version=8)
    onnx.save(model, str(path))
    return w, bias


def _conv_reference(x, w, bias):
    B = x.shape[0]
    p = x.reshape(B, 3, 4, 8, 4, 8).transpose(0, 2, 4, 1, 3, 5).reshape(B, 4, 4, -1)
    return np.einsum("bijk,ck->bcij", p, w.reshape(4, -1)) + bias[None, :, None, None]


@pytest.mark.parametrize("tokens", [False, True])
def test_onnx_extractor_matches_numpy(tmp_path, tokens):
    w, bias = _tiny_encoder(tmp_path / "enc.onnx", tokens)
    rng = np.random.default_rng(4)
    images = rng.integers(0, 256, (2, 50, 70, 3), dtype=np.uint8)
    masks = np.zeros((2, 50, 70), bool)
    masks[0, 5:30, 10:60] = True
    masks[1, 20:45, 30:40] = True
    ex = OnnxExtractor(tmp_path / "enc.onnx", size=32, skip_tokens=1 if tokens else 0)
    got = ex.extract(images, masks).feats
    crops, _ = crop_square(images, masks, 32, 0.1)
    x = (crops.transpose(0, 3, 1, 2) / 255.0 - ex.mean) / ex.std
    fmap = _conv_reference(x, w, bias)                           # (B, 4, 4, 4)
    ref = fmap.reshape(2, -1) if not tokens else fmap.reshape(2, 4, 16).transpose(0, 2, 1)[:, 1:]
    ref = ref.reshape(2, -1)
    ref = ref / np.linalg.norm(ref, axis=1, keepdims=True)
    np.testing.assert_allclose(got, ref, atol=1e-5)


def test_onnx_extractor_bad_model(tmp_path):
    (tmp_path / "bad.onnx").write_bytes(b"not a model")
    with pytest.raises(ValueError, match="bad.onnx"):
        OnnxExtractor(tmp_path / "bad.onnx")
