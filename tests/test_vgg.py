"""The paper's l_vgg (ucad_cl/vgg.py): masked Gram matrices against NumPy, the ONNX contract's
errors, and the Levenberg-Marquardt refinement of the fitted colours (pixels drawn from the
light model itself, a small random convolutional network as the feature extractor: no VGG
weights ship or download)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from ucad_cl.colorimetry import delta_e2000, linear_to_lab


def tiny_net(tmp_path: Path, *, config: dict | None = None, seed: int = 0,
             fixed: tuple[int, int] | None = None, flat: bool = False) -> str:
    """onnx:MODEL:CONFIG of two 3 x 3 convolutions with ReLU (8 channels, the second at stride
    2), both feature maps as outputs ``f1`` and ``f2``; fixed random weights. ``fixed``: the
    input's (H, W) fixed in the graph; ``flat``: ``f2`` pooled to (N, 8) instead."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    rng = np.random.default_rng(seed)
    w1 = rng.normal(0, 0.5, (8, 3, 3, 3)).astype(np.float32)
    b1 = rng.normal(0, 0.1, 8).astype(np.float32)
    w2 = rng.normal(0, 0.3, (8, 8, 3, 3)).astype(np.float32)
    b2 = rng.normal(0, 0.1, 8).astype(np.float32)
    nodes = [helper.make_node("Conv", ["x", "w1", "b1"], ["c1"], pads=[1, 1, 1, 1]),
             helper.make_node("Relu", ["c1"], ["f1"]),
             helper.make_node("Conv", ["f1", "w2", "b2"], ["c2"], pads=[1, 1, 1, 1],
                              strides=[2, 2]),
             helper.make_node("Relu", ["c2"], ["r2" if flat else "f2"])]
    if flat:
        nodes += [helper.make_node("GlobalAveragePool", ["r2"], ["p2"]),
                  helper.make_node("Flatten", ["p2"], ["f2"])]
    dims = ["N", 3, *(fixed or ("H", "W"))]
    graph = helper.make_graph(
        nodes, "tiny", [helper.make_tensor_value_info("x", TensorProto.FLOAT, dims)],
        [helper.make_tensor_value_info("f1", TensorProto.FLOAT, None),
         helper.make_tensor_value_info("f2", TensorProto.FLOAT, None)],
        initializer=[numpy_helper.from_array(a, n)
                     for a, n in ((w1, "w1"), (b1, "b1"), (w2, "w2"), (b2, "b2"))])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)])
    model.ir_version = 8
    onnx.save(model, str(tmp_path / "tiny.onnx"))
    cfg = {"input_size": [64, 80], "mean": [0.485, 0.456, 0.406], "std": [0.229, 0.224, 0.225]}
    cfg.update(config or {})
    (tmp_path / "tiny.json").write_text(json.dumps(cfg))
    return f"onnx:{tmp_path / 'tiny.onnx'}:{tmp_path / 'tiny.json'}"


def test_masked_grams_equal_numpy_sums_of_outer_products():
    """masked_grams against the definition written out pixel by pixel (NumPy outer products),
    soft and empty masks included."""
    from ucad_cl.vgg import masked_grams

    rng = np.random.default_rng(4)
    fmap = rng.normal(size=(2, 5, 6, 7))
    masks = np.zeros((3, 6, 7))
    masks[0, 1:4, 2:6] = 1.0
    masks[1] = rng.random((6, 7)) * (rng.random((6, 7)) > 0.5)
    got = masked_grams(fmap, masks)
    assert got.shape == (2, 3, 5, 5)
    for n in range(2):
        for p in range(2):
            want = np.zeros((5, 5))
            for i in range(6):
                for j in range(7):
                    f = fmap[n, :, i, j]
                    want += masks[p, i, j] * np.outer(f, f)
            np.testing.assert_allclose(got[n, p], want / masks[p].sum(), rtol=1e-12)
        assert not got[n, 2].any()                       # an empty mask: zeros


def test_onnx_features_contract_errors_name_the_file(tmp_path):
    """A config or model outside the contract: ValueError (or FileNotFoundError) naming it."""
    from ucad_cl.vgg import OnnxFeatures

    spec = tiny_net(tmp_path)
    f = OnnxFeatures.from_spec(spec)
    maps = f.maps(np.zeros((3, 64, 80, 3)))
    assert [m.shape for m in maps] == [(3, 8, 64, 80), (3, 8, 32, 40)]
    model, cfg = tmp_path / "tiny.onnx", tmp_path / "tiny.json"
    bad = tmp_path / "bad.json"
    for text, match in (('{"mean": [0, 0, 0]}', "input_size"), ("{not json", "not JSON"),
                        ('{"input_size": [64]}', "input_size"),
                        ('{"input_size": [64, 100000]}', "input_size"),
                        ('{"input_size": [64, 80], "std": [0, 1, 1]}', "std"),
                        ('{"input_size": [64, 80], "outputs": ["relu9"]}', "relu9"),
                        ('{"input_size": [64, 80], "layer_weights": [1]}', "layer_weights")):
        bad.write_text(text)
        with pytest.raises(ValueError, match=match) as exc:
            OnnxFeatures(model, bad)
        assert "bad" in str(exc.value) or "tiny.onnx" in str(exc.value)
    with pytest.raises(FileNotFoundError, match="nowhere.onnx"):
        OnnxFeatures(tmp_path / "nowhere.onnx", cfg)
    (tmp_path / "junk.onnx").write_bytes(b"not a model")
    with pytest.raises(ValueError, match="junk.onnx"):
        OnnxFeatures(tmp_path / "junk.onnx", cfg)
    with pytest.raises(ValueError, match="onnx:MODEL:CONFIG"):
        OnnxFeatures.from_spec(f"onnx:{model}")
    # checked when loaded, by one run on a blank image: an input size the graph refuses, an
    # output that is no feature map
    (tmp_path / "fixed").mkdir()
    with pytest.raises(ValueError, match=r"tiny.onnx: the model \(input_size \[64, 80\]\) "
                                         r"fails on a \(1, 3, 64, 80\) input"):
        OnnxFeatures.from_spec(tiny_net(tmp_path / "fixed", fixed=(32, 32)))
    (tmp_path / "flat").mkdir()
    with pytest.raises(ValueError, match=r"output 'f2' must be \(N, C, h, w\)"):
        OnnxFeatures.from_spec(tiny_net(tmp_path / "flat", flat=True))


def _scene(rng, h=48, w=64):
    """Samples of three parts (paint, tyre, metal) on a (h, w) frame, the light model's own
    pixels under a known light: (samples, pixels (rows, cols), photo uint8, truth, light)."""
    from ucad_cl.colorimetry import linear_to_srgb8, srgb8_to_linear
    from ucad_cl.light import Lighting, Samples, predict, sun_direction

    yy, xx = np.mgrid[0:h, 0:w]
    part_map = np.full((h, w), -1)
    part_map[8:30, 6:58] = 0
    part_map[30:44, 8:24] = 1
    part_map[30:44, 40:56] = 2
    rows, cols = np.nonzero(part_map >= 0)
    part = part_map[rows, cols]
    n = len(part)
    nrm = np.stack([np.sin(xx / 9.0), 0.6 + 0.3 * np.cos(yy / 7.0), np.ones((h, w))], -1)
    nrm = nrm[rows, cols]
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    view = np.tile([0.0, 0.2, 1.0], (n, 1)) / np.hypot(0.2, 1.0)
    truth = np.array([[0.45, 0.07, 0.05], [0.04, 0.04, 0.04], [0.55, 0.57, 0.6]])
    s = Samples(rgb=np.zeros((n, 3)), normal=nrm, view=view, part=part,
                coat=np.array([1.0, 0.0, 0.0])[part], metallic=np.array([0.0, 0.0, 1.0])[part],
                roughness=np.array([0.3, 0.9, 0.3])[part])
    d = sun_direction(40.0, 35.0)
    sky = np.full(3, 0.35)
    light = Lighting(sky=sky, sun=(1 - sky) / d[1], sun_dir=d)
    photo = np.full((h, w, 3), 90, np.uint8)
    photo[rows, cols] = linear_to_srgb8(predict(s, light, truth))
    s.rgb = srgb8_to_linear(photo[rows, cols])
    return s, (rows, cols), photo, truth, light


def test_refinement_reaches_the_true_colours_from_a_wrong_start(tmp_path):
    """From colours 20-40 % off (the light known), the refinement of l_rgb + 0.1 l_stat + l_vgg
    comes back within CIEDE2000 1 of the truth, the total and l_vgg fall, and the same input
    gives the same bytes."""
    from ucad_cl.light import LightFit
    from ucad_cl.vgg import OnnxFeatures, refine_colours

    s, pixels, photo, truth, light = _scene(np.random.default_rng(1))
    f = OnnxFeatures.from_spec(tiny_net(tmp_path))
    start = truth * np.array([[1.3, 0.8, 1.2], [1.4, 1.4, 1.4], [0.75, 0.8, 0.8]])
    fit = LightFit(lighting=light, albedo=start, loss=0.0, kept=np.ones(len(s.part), bool))
    out, info = refine_colours(f, photo, s, pixels, fit)
    for p in range(3):
        de = float(delta_e2000(linear_to_lab(out.albedo[p]), linear_to_lab(truth[p])))
        assert de < 1.0, (p, out.albedo[p], truth[p], de)
    assert info.loss_after < info.loss_before and info.vgg_after < 0.2 * info.vgg_before, info
    assert info.jacobians >= 1 and info.images >= 1 + 9 + 1
    again, info2 = refine_colours(f, photo, s, pixels, fit)
    assert again.albedo.tobytes() == out.albedo.tobytes() and info2.loss_after == info.loss_after
    # at the truth the refinement stays there (both terms are at their least)
    fit0 = LightFit(lighting=light, albedo=truth.copy(), loss=0.0, kept=fit.kept)
    same, _ = refine_colours(f, photo, s, pixels, fit0)
    assert np.abs(same.albedo - truth).max() < 5e-3


def test_vgg_weight_zero_is_the_light_models_objective(tmp_path):
    """With weight 0 the refinement minimises l_rgb + 0.1 l_stat alone: it never ends above
    the closed form's objective, and l_vgg is reported but not followed."""
    from ucad_cl.light import LightFit, objective, solve_albedo
    from ucad_cl.vgg import OnnxFeatures, refine_colours

    s, pixels, photo, truth, light = _scene(np.random.default_rng(2))
    f = OnnxFeatures.from_spec(tiny_net(tmp_path, config={"weight": 0.0}))
    a0 = solve_albedo(s, light, 3)
    fit = LightFit(lighting=light, albedo=a0, loss=0.0, kept=np.ones(len(s.part), bool))
    out, info = refine_colours(f, photo, s, pixels, fit)
    assert info.weight == 0.0
    assert objective(s, light, out.albedo, 3) <= objective(s, light, a0, 3) + 1e-15
    assert out.loss == pytest.approx(objective(s, light, out.albedo, 3), rel=1e-12)


def test_gauss_newton_gradient_is_half_the_objectives_numerical_gradient():
    """J^T r of l_rgb + 0.1 l_stat (``vgg._BaseTerm``, from per-part sums) is half the gradient
    of ``light.objective`` (computed pixel by pixel) by central differences, at several
    colours, with a coated, a matte and a metal part, reflection folded on one."""
    from ucad_cl.light import objective, shading
    from ucad_cl.vgg import _BaseTerm

    s, _, _, truth, light = _scene(np.random.default_rng(5))
    light.coat_scale = np.array([0.0, 1.0, 1.0])
    term = _BaseTerm(s, *shading(s, light), np.arange(3))
    for a in (truth, truth * 1.3, truth * np.array([0.5, 1.0, 2.0])):
        jtj, jtr = term.normal(a)
        num = np.zeros(9)
        for k in range(9):
            hi, lo = a.copy(), a.copy()
            hi.flat[k] += 1e-6
            lo.flat[k] -= 1e-6
            num[k] = (objective(s, light, hi, 3) - objective(s, light, lo, 3)) / 2e-6
        np.testing.assert_allclose(jtr, num / 2, rtol=1e-5, atol=1e-9)
        assert np.all(np.diag(jtj) > 0) and not (jtj - np.diag(np.diag(jtj))).any()
