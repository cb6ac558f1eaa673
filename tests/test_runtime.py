"""The split network at every precision: OpenVINO's cut graphs compute what the whole graph computes,
the shipped int8 variant stays close to fp32, and a folder without the variant is refused clearly."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from shared.model.net import AllCuts, SplitKeypointNet
from shared.model.openvino_net import OpenVINOSplitNet, VariantError, compile_full, export_ir, variant_path
from shared.model.precision import cpu_flags, resolve_for_folder, resolve_precision
from shared.model.runtime import calibrate_cumulative_ms, load_split_net
from shared.vision.metrics import e_px
from shared.wire.cuts import CUTS, N_CUTS

MODELS = Path(__file__).resolve().parent.parent / "models"


def _rois(n: int, seed: int = 0) -> np.ndarray:
    """Tag-like ROIs: a dark square with a random bit pattern on a bright border, plus noise."""
    rng = np.random.default_rng(seed)
    out = np.full((n, 256, 256), 200, np.uint8)
    for i in range(n):
        cells = rng.integers(0, 2, (8, 8)) * 170 + 20
        cells[0, :] = cells[-1, :] = cells[:, 0] = cells[:, -1] = 20
        out[i, 51:205, 51:205] = np.kron(cells, np.ones((20, 20)))[:154, :154]
    noisy = out.astype(np.int16) + rng.integers(-8, 9, out.shape)
    return np.clip(noisy, 0, 255).astype(np.uint8)


@pytest.fixture(scope="module")
def float_ir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The untrained network's all-cuts graph as IR (random but fixed weights, BatchNorm in eval)."""
    torch.manual_seed(0)
    net = SplitKeypointNet(roi_margin=0.2).eval()
    for p in net.fc[-1].parameters():  # non-zero offsets, so the tail's output depends on its input
        torch.nn.init.normal_(p, std=0.01)
    return export_ir(AllCuts(net), tmp_path_factory.mktemp("ir"))


@pytest.mark.parametrize("k", [c.k for c in CUTS])
def test_openvino_head_then_tail_equals_the_whole_graph(float_ir: Path, k: int) -> None:
    net = OpenVINOSplitNet(float_ir, threads=1)
    rois = _rois(3)
    whole = compile_full(float_ir, threads=1)(rois)
    z = net.head(rois, k)
    assert z.shape[0] == 3 and z.shape[1:] == CUTS[k].shape
    np.testing.assert_allclose(net.tail(z, k), whole, atol=1e-5)


def test_openvino_tail_at_zero_takes_the_roi_pixels(float_ir: Path) -> None:
    net = OpenVINOSplitNet(float_ir, threads=1)
    rois = _rois(2, seed=1)
    np.testing.assert_allclose(net.tail(rois, 0), net.tail(net.head(rois, 0), 0), atol=1e-6)


def test_torch_tail_at_zero_takes_the_roi_pixels_or_heads_floats_alike() -> None:
    """An integrator's `tail(head(rois, 0), 0)` (docs/int8.md) cast the normalised floats to uint8 on the
    PyTorch path: 7 ROI px off, while OpenVINO's took them."""
    net = load_split_net(MODELS, "fp32")
    rois = _rois(2, seed=3)
    np.testing.assert_allclose(net.tail(net.head(rois, 0), 0), net.tail(rois, 0), atol=1e-6)
    np.testing.assert_allclose(net.tail(net.head(rois, 3), 3), net.tail(rois, 0), atol=1e-4)


def test_a_folder_without_the_int8_variant_is_refused_with_what_it_has(tmp_path: Path) -> None:
    for name in ("config.json", "model.safetensors"):
        shutil.copy(MODELS / name, tmp_path / name)
    config = json.loads((tmp_path / "config.json").read_text())
    config.pop("variants", None)
    (tmp_path / "config.json").write_text(json.dumps(config))
    with pytest.raises(VariantError, match=r"no 'int8' variant.*splittag quantize"):
        load_split_net(tmp_path, "int8")
    with pytest.raises(ValueError, match="precision must be one of"):
        load_split_net(tmp_path, "int4")  # type: ignore[arg-type]


# /proc/cpuinfo excerpts of the three CPU kinds we meet (flags cut to what decides the precision).
ZEN3 = "processor\t: 0\nmodel name\t: AMD EPYC\nflags\t\t: fpu sse4_2 avx fma avx2 sha_ni\n"
ZEN4 = "processor\t: 0\nflags\t\t: fpu avx avx2 avx512f avx512_vnni avx512_bf16\n"
SPR = "processor\t: 0\nflags\t\t: fpu avx avx2 avx512f avx512_vnni avx512_bf16 amx_bf16 amx_int8\n"


def test_auto_precision_never_picks_emulated_bf16() -> None:
    """auto: int8 where the folder has it; else bf16 only with hardware bf16 (PyTorch emulates it on
    AVX2, 9x slower than fp32 on Zen 3); an explicit choice is taken as given."""
    assert cpu_flags(ZEN3) >= {"avx2"} and "avx512_bf16" not in cpu_flags(ZEN3)
    assert cpu_flags("no flags here") == frozenset()
    for cpuinfo in (ZEN3, ZEN4, SPR):
        assert resolve_precision("auto", variants={"int8"}, flags=cpu_flags(cpuinfo)) == "int8"
    assert resolve_precision("auto", variants=(), flags=cpu_flags(ZEN3)) == "fp32"
    assert resolve_precision("auto", variants=(), flags=cpu_flags(ZEN4)) == "bf16"
    assert resolve_precision("auto", variants=(), flags=cpu_flags(SPR)) == "bf16"
    assert resolve_precision("auto", variants={"int8"}, flags={"sse4_2"}) == "fp32"  # no AVX2: no OpenVINO int8
    assert resolve_precision("bf16", variants={"int8"}, flags=cpu_flags(ZEN3)) == "bf16"
    with pytest.raises(ValueError, match="precision must be one of"):
        resolve_precision("int4", variants=(), flags=())  # type: ignore[arg-type]


def test_auto_precision_reads_the_folder(tmp_path: Path) -> None:
    assert resolve_for_folder("auto", MODELS, ZEN3) == "int8"  # the shipped folder lists int8
    (tmp_path / "config.json").write_text(json.dumps({"variants": {}}))
    assert resolve_for_folder("auto", tmp_path, ZEN3) == "fp32"
    assert resolve_for_folder("auto", tmp_path, SPR) == "bf16"
    (tmp_path / "config.json").write_text("{not json")
    assert resolve_for_folder("auto", tmp_path, ZEN4) == "bf16"
    net = load_split_net(MODELS, "auto", threads=1)
    assert net.precision == resolve_for_folder("auto", MODELS)


def test_a_listed_variant_whose_files_are_missing_is_refused(tmp_path: Path) -> None:
    config = json.loads((MODELS / "config.json").read_text())
    config["variants"] = {"int8": {"format": "openvino-ir", "path": "int8/model.xml"}}
    (tmp_path / "config.json").write_text(json.dumps(config))
    with pytest.raises(VariantError, match="missing"):
        variant_path(tmp_path, "int8")


def test_the_first_convolution_runs_on_an_exactly_quantised_image(float_ir: Path, tmp_path: Path) -> None:
    """shared.model.int8_graph: the rewritten first convolution sees every 8-bit pixel exactly (x' =
    (u - 128) / 128 on an int8 grid) and only its weights are rounded: inside the one-pixel border its
    output (block 1's first layer, before the FakeQuantize that follows in an int8 graph) is the fp32
    layer's to within the int8 weight step; cut-by-cut the graph still splits exactly."""
    import openvino as ov

    from shared.model.int8_graph import INPUT_SCALE, INPUT_SHIFT, first_convolution_exact_int8

    def first_layer(model: ov.Model) -> ov.Model:
        """The first convolution's output with its bias, if it has one."""
        conv = next(op for op in model.get_ordered_ops() if op.get_type_name() == "Convolution")
        (user,) = (t.get_node() for t in conv.output(0).get_target_inputs())
        out = user if user.get_type_name() == "Add" else conv
        return ov.Model([out.output(0)], model.get_parameters(), "first")

    core = ov.Core()
    config = {"INFERENCE_NUM_THREADS": 1, "INFERENCE_PRECISION_HINT": "f32"}
    rewritten = first_convolution_exact_int8(core.read_model(float_ir))
    x = (_rois(2, seed=3).astype(np.float32) / 127.5 - 1.0).reshape(2, 1, 256, 256)
    ref = core.compile_model(first_layer(core.read_model(float_ir)), "CPU", config)(x)[0]
    got = core.compile_model(first_layer(rewritten), "CPU", config)(x)[0]
    conv = next(op for op in core.read_model(float_ir).get_ordered_ops() if op.get_type_name() == "Convolution")
    weights = conv.input_value(1).get_node().get_data().astype(np.float64)  # (C, 1, 3, 3), no bias here
    # what the layer must compute: the exact image x' = (u - 128) / 128, weights a W rounded per channel
    scaled = INPUT_SCALE * weights
    step = np.abs(scaled).reshape(len(scaled), -1).max(axis=1).reshape(-1, 1, 1, 1) / 127
    u = _rois(2, seed=3).astype(np.float64).reshape(2, 1, 256, 256)
    exact = torch.nn.functional.conv2d(
        torch.from_numpy((u - 128) / 128), torch.from_numpy(np.round(scaled / step) * step), padding=1
    ).numpy() + INPUT_SHIFT * weights.sum(axis=(1, 2, 3)).reshape(1, -1, 1, 1)
    np.testing.assert_allclose(got, exact, atol=2e-5 * float(np.abs(exact).max()))
    # against the fp32 layer: half an int8 weight step per tap inside; the border's padding is u = 128
    bound = (np.abs(scaled).reshape(len(scaled), -1).max(axis=1) / 127 / 2 * 9).reshape(1, -1, 1, 1)
    assert np.all(np.abs(got - ref)[:, :, 1:-1, 1:-1] <= bound + 1e-5)
    border = INPUT_SHIFT * np.abs(weights).sum(axis=(1, 2, 3)).reshape(1, -1, 1, 1)
    assert np.all(np.abs(got - ref) <= bound + border + 1e-5)
    path = tmp_path / "model.xml"
    ov.save_model(rewritten, str(path), compress_to_fp16=False)
    net, rois = OpenVINOSplitNet(path, threads=1), _rois(2, seed=4)
    whole = compile_full(path, threads=1)(rois)
    for k in range(N_CUTS):
        np.testing.assert_allclose(net.tail(net.head(rois, k), k), whole, atol=1e-5)


def test_shipped_int8_variant_splits_like_fp32_and_stays_close_to_it() -> None:
    """Every cut gives the whole int8 graph's output, and on these toy ROIs (a bit pattern, far from the
    training data) the keypoints stay on the lattice fp32 finds (within 5 of the lattice's ~51 ROI px
    spacing). The accuracy on real test data (+0.0012 px) is measured by `splittag eval --precision int8`
    and bench/model --data, not here."""
    fp32, int8 = load_split_net(MODELS, "fp32"), load_split_net(MODELS, "int8", threads=1)
    rois = _rois(4, seed=2)
    ref = fp32.tail(fp32.head(rois, 0), 0)
    whole = int8.tail(rois, 0)
    for k in range(N_CUTS):
        np.testing.assert_allclose(int8.tail(int8.head(rois, k), k), whole, atol=1e-5)
    assert float(e_px(whole, ref).max()) < 5.0


def test_the_robot_calibration_times_every_cut_of_either_runtime(float_ir: Path) -> None:
    ms = calibrate_cumulative_ms(OpenVINOSplitNet(float_ir, threads=1), repetitions=1)
    assert len(ms) == N_CUTS and all(t >= 0 for t in ms)


def test_onnx_halves_run_in_onnx_runtime_like_the_weights(tmp_path: Path) -> None:
    """`splittag export`: head 3 then tail 3 in ONNX Runtime give PyTorch fp32's keypoints; the manifest
    says what each file takes and returns."""
    import onnxruntime as ort

    from shared.model.export import export

    manifest = json.loads(export(MODELS, tmp_path, fmt="onnx", precision="fp32", cuts=(3,)).read_text())
    assert [(f["side"], f["k"]) for f in manifest["files"]] == [("head", 3), ("tail", 3)]
    head, tail = (ort.InferenceSession(str(tmp_path / f["file"])) for f in manifest["files"])
    rois = _rois(2, seed=3)
    z = head.run(None, {"roi": rois[:, None]})[0]
    assert z.shape == (2, *CUTS[3].shape) and manifest["files"][1]["input"]["name"] == "cut3"
    kp = tail.run(None, {"cut3": z})[0]
    fp32 = load_split_net(MODELS, "fp32")
    np.testing.assert_allclose(kp, fp32.tail(rois, 0), atol=2e-5)
    # each file is whole: the weights inside, nothing beside it that the manifest does not name (a trial
    # copied the listed files and got graphs that did not load)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["head_3.onnx", "manifest.json", "tail_3.onnx"]
    assert all(f["needs"] == [f["file"]] for f in manifest["files"])


def test_openvino_halves_take_the_uint8_roi_and_match_the_services_int8(tmp_path: Path) -> None:
    """The exported int8 IR, compiled with the manifest's settings, gives the services' int8 keypoints
    exactly; its head takes the uint8 ROI as the ONNX head does (it took the normalised float ROI, and a
    uint8 one went in silently, keypoints 21 px off), and the manifest says to compile in f32 (a CPU
    with bf16 otherwise runs its float parts in bf16: a trial's keypoints moved by up to 0.9 px)."""
    import openvino as ov

    from shared.tools.cli import main

    assert main(["export", "--out", str(tmp_path), "--format", "openvino", "--precision", "int8", "--ks", "3"]) == 0
    manifest = json.loads((tmp_path / "manifest.json").read_text())
    head_file, tail_file = manifest["files"]
    assert head_file["input"] == {"name": "roi", "shape": [-1, 1, 256, 256], "dtype": "uint8"}
    assert manifest["openvino_compile"]["INFERENCE_PRECISION_HINT"] == "f32"
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        ["manifest.json", *head_file["needs"], *tail_file["needs"]]
    )
    core = ov.Core()
    head, tail = (
        core.compile_model(str(tmp_path / f["file"]), "CPU", manifest["openvino_compile"])
        for f in (head_file, tail_file)
    )
    rois = _rois(2, seed=5)
    z = head({"roi": rois[:, None]})[head_file["output"]["name"]]  # (outputs by the manifest's names)
    kp = tail({tail_file["input"]["name"]: z})[tail_file["output"]["name"]]
    int8 = load_split_net(MODELS, "int8")
    np.testing.assert_allclose(kp, int8.tail(int8.head(rois, 3), 3), atol=1e-6)
    # fp32 IR alike (uint8 in, the float graph's keypoints), into the same folder: the int8 files go
    assert main(["export", "--out", str(tmp_path), "--format", "openvino", "--ks", "7"]) == 0
    fp32_doc = json.loads((tmp_path / "manifest.json").read_text())
    assert sorted(p.name for p in tmp_path.iterdir()) == ["head_7.bin", "head_7.xml", "manifest.json"]
    head7 = core.compile_model(str(tmp_path / "head_7.xml"), "CPU", fp32_doc["openvino_compile"])
    kp7 = head7({"roi": rois[:, None]})["keypoints"]
    np.testing.assert_allclose(kp7, load_split_net(MODELS, "fp32").tail(rois, 0), atol=1e-4)


def test_the_export_command_makes_int8_onnx_and_says_what_it_cost(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The command calibrates on generated ROIs (or a data set), checks on held-out ones, prints the cost
    and records where both came from; counts it cannot use are refused by the parser."""
    from shared.tools.cli import main

    argv = ["export", "--out", str(tmp_path), "--format", "onnx", "--precision", "int8", "--ks", "7"]
    assert main([*argv, "--calibration-samples", "8", "--evaluation-samples", "8"]) == 0
    out = capsys.readouterr().out
    assert "wrote 1 graphs for k = 7" in out and "int8 on 8 held-out ROIs: e_px" in out, out
    doc = json.loads((tmp_path / "manifest.json").read_text())
    assert doc["calibration"]["samples"] == 8 and "seeds 9001 + 100 i" in doc["calibration"]["source"]
    assert len(doc["weights"]["sha256"]["model.safetensors"]) == 64 and "pyrDown" in doc["roi"]["warp"]
    assert doc["accuracy"]["samples"] == 8 and [f["file"] for f in doc["files"]] == ["head_7.onnx"]
    with pytest.raises(SystemExit):
        main([*argv, "--calibration-samples", "0"])
    assert "must be >= 1" in capsys.readouterr().err
    assert main(["export", "--out", str(tmp_path), "--calibration-data", str(tmp_path)]) == 2
    assert "--calibration-data: for --format onnx --precision int8 only" in capsys.readouterr().err
    assert main(["export", "--out", str(tmp_path), "--format", "openvino", "--calibration-samples", "5"]) == 2
    assert main([*argv, "--calibration-data", str(tmp_path / "nowhere")]) == 2  # one line, no traceback
    assert "not a splittag data set" in capsys.readouterr().err
    # A failed export leaves the one the folder holds as it was (a trial's was deleted) ...
    assert main(["export", "--out", str(tmp_path), "--weights", str(tmp_path / "nope"), "--ks", "3"]) == 2
    assert json.loads((tmp_path / "manifest.json").read_text()) == doc
    assert sorted(p.name for p in tmp_path.iterdir()) == ["head_7.onnx", "manifest.json"]
    # ... one that succeeds replaces it whole and says so; a file is no folder
    assert main(["export", "--out", str(tmp_path), "--format", "openvino", "--ks", "7"]) == 0
    assert "replacing the 2 files of the export it held" in capsys.readouterr().out
    assert main(["export", "--out", str(tmp_path / "manifest.json")]) == 2
    assert "is a file: give a folder" in capsys.readouterr().err


def test_int8_onnx_halves_for_onnx_runtime_are_one_quantised_graph_cut_at_k(tmp_path: Path) -> None:
    """A trial's robot ran ONNX Runtime and found no int8 graph for it. Quantised here (every Conv but the
    first, each with its ReLU, calibrated on ROIs of the training generator), cut at k by tensor name:
    head 3 then tail 3 is the whole int8 graph (tail 0), and the manifest gives what int8 costs on
    held-out ROIs."""
    import onnx
    import onnxruntime as ort

    from shared.datasets.synth import CALIBRATION_SEED, EVALUATION_SEED, mixed_rois
    from shared.model.export import export

    calibration, _ = mixed_rois(16, CALIBRATION_SEED)
    held_out = mixed_rois(16, EVALUATION_SEED)
    doc = json.loads(
        export(
            MODELS, tmp_path, fmt="onnx", precision="int8", cuts=(0, 3), calibration=calibration, evaluation=held_out
        ).read_text()
    )
    assert [(f["side"], f["k"]) for f in doc["files"]] == [("head", 3), ("tail", 0), ("tail", 3)]
    assert doc["calibration"]["samples"] == 16
    # loadable by ONNX Runtime 1.17 (a trial's robot on an older runtime met the exporter's IR 10)
    assert (doc["onnx"]["ir_version"], doc["onnx"]["opset"]) == (9, 20)
    assert "corners[[3, 2, 1, 0]] - 0.5" in doc["roi"]["quad"] and "finite" in doc["roi"]["checks"]
    accuracy = doc["accuracy"]
    assert accuracy["samples"] == 16 and abs(accuracy["e_px_change"]) < 0.05 and accuracy["moved_px_p99"] < 0.5
    graph = onnx.load(str(tmp_path / "tail_0.onnx")).graph
    convs = [n for n in graph.node if n.op_type == "Conv"]
    quantised = {o for n in graph.node if n.op_type == "DequantizeLinear" for o in n.output}
    assert not set(convs[0].input) & quantised and all(set(c.input) & quantised for c in convs[1:])
    # Each quantised convolution's ReLU is folded into its output grid (zero point 0), not rounded once on
    # a grid spanning the negative values it then zeroes and again after it (0.062 -> 0.036 px moved on
    # the real photos, ad hoc): no ReLU is left behind a dequantised tensor.
    relus = [n for n in graph.node if n.op_type == "Relu"]
    assert relus and not any(set(n.input) & quantised for n in relus)
    after_conv = {o for c in convs[1:] for o in c.output}
    conv_grids = [n for n in graph.node if n.op_type == "QuantizeLinear" and n.input[0] in after_conv]
    zero_points = {i.name: i for i in graph.initializer}
    assert len(conv_grids) == len(convs) - 1
    assert all(int(onnx.numpy_helper.to_array(zero_points[n.input[2]])) == 0 for n in conv_grids)
    head, tail, whole = (ort.InferenceSession(str(tmp_path / f)) for f in ("head_3.onnx", "tail_3.onnx", "tail_0.onnx"))
    rois = held_out[0][:4]
    z = head.run(None, {"roi": rois[:, None]})[0]
    kp = tail.run(None, {"cut3": z})[0]
    # The tail starts on the head's uint8 grid, as inside the whole graph (a trial: without it the tail's
    # first convolution ran in fp32, 1.8x slower, a rounding step from the whole graph)
    np.testing.assert_allclose(kp, whole.run(None, {"roi": rois[:, None]})[0], atol=1e-6)
    tail_graph = onnx.load(str(tmp_path / "tail_3.onnx")).graph
    first = next(n for n in tail_graph.node if n.op_type == "Conv")
    assert first.input[0] in {o for n in tail_graph.node if n.op_type == "DequantizeLinear" for o in n.output}
    grid = doc["files"][0]["output"]["uint8_grid"]
    assert grid == doc["files"][2]["input"]["uint8_grid"] and grid["scale"] > 0
    codes = np.round(z / grid["scale"]) + grid["zero_point"]  # it may travel as its uint8 codes, exactly
    assert codes.min() >= 0 and codes.max() <= 255
    np.testing.assert_allclose(grid["scale"] * (codes - grid["zero_point"]), z, atol=1e-6)


@pytest.mark.parametrize("precision", ["fp32", "int8"])
def test_the_split_api_refuses_float_rois_and_another_cuts_tensor(precision: str) -> None:
    """A trial: `head(rois / 255, 3)` was taken silently and gave a cut tensor 7 away from the right one,
    and `tail(cut3, 5)` came back as the runtime's raw shape error. Both are refused, saying what fits."""
    net = load_split_net(MODELS, precision)  # type: ignore[arg-type]
    rois = _rois(2, seed=7)
    with pytest.raises(TypeError, match="head takes uint8 ROIs"):
        net.head(rois.astype(np.float32) / 255, 3)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"head takes ROIs \(N, 256, 256\), got \[2, 128, 128\]"):
        net.head(rois[:, ::2, ::2], 3)
    z3 = net.head(rois, 3)
    with pytest.raises(ValueError, match=r"tail at k=5 \(block5\) takes \(N, 256, 8, 8\)"):
        net.tail(z3, 5)
    assert net.tail(z3, 3).shape == (2, 16, 2) and net.tail(rois, 0).shape == (2, 16, 2)


def test_profile_prints_the_cpu_first(capsys: pytest.CaptureFixture[str]) -> None:
    """README says every benchmark prints its CPU first; `splittag profile`, the paper's table of C(k),
    did not (a researcher's reproduction had figures without the machine they came from)."""
    from shared.runtime.cpus import cpu_label
    from shared.tools.cli import main

    argv = ["profile", "--weights", str(MODELS), "--variant", "fp32", "--repetitions", "1"]
    assert main(argv) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == f"CPU: {cpu_label()}"
    assert len(lines) == 2 + 1 + N_CUTS  # the CPU, the caption, the header, a row per cut


def test_the_cpu_label_names_model_family_and_features() -> None:
    from shared.runtime.cpus import cpu_label

    info = "model name\t: AMD EPYC 9R14\ncpu family\t: 25\nmodel\t\t: 17\nflags\t\t: fpu avx2 avx512f avx512_bf16\n"
    label = cpu_label(info)
    assert label.startswith("AMD EPYC 9R14 (family 25 model 17), ")
    assert label.endswith("AVX-512 bf16 + AVX-512 + AVX2, no AMX")
