"""Evaluation metrics (paper protocol), figures and the error-against-run-time report."""

import json
import math

import numpy as np
import pytest
import torch

from evdnerf_ros.errors import InputError
from evdnerf_ros.eval import (PSNR_CAP_DB, brightness_align, event_metrics, mae, markdown_table,
                              plot_runs, protocol_windows, psnr, quantize_log_change,
                              read_metrics, run_report, side_by_side, ssim)
from evdnerf_ros.eval.metrics import gaussian_kernel_1d
from evdnerf_ros.events import counts_from_log_change

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _ssim_loop(x, y, r, size=11, sigma=1.5):
    """Direct per-pixel SSIM with explicit 2-D Gaussian weights (reference implementation)."""
    ax = np.arange(size) - (size - 1) / 2
    w = np.exp(-(ax[:, None] ** 2 + ax[None, :] ** 2) / (2 * sigma ** 2))
    w /= w.sum()
    c1, c2 = (0.01 * r) ** 2, (0.03 * r) ** 2
    vals = []
    for i in range(x.shape[0] - size + 1):
        for j in range(x.shape[1] - size + 1):
            px, py = x[i:i + size, j:j + size], y[i:i + size, j:j + size]
            mx, my = (w * px).sum(), (w * py).sum()
            vx, vy = (w * (px - mx) ** 2).sum(), (w * (py - my) ** 2).sum()
            cxy = (w * (px - mx) * (py - my)).sum()
            vals.append((2 * mx * my + c1) * (2 * cxy + c2) / ((mx ** 2 + my ** 2 + c1) * (vx + vy + c2)))
    return float(np.mean(vals))


def _ssim_torch(x, y, r):
    """torchmetrics-style: reflect pad, 2-D Gaussian conv, crop the padded border."""
    g = torch.tensor(gaussian_kernel_1d(), dtype=torch.float64)
    k = (g[:, None] * g[None, :])[None, None]
    X = torch.tensor(x)[None, None]
    Y = torch.tensor(y)[None, None]
    f = lambda z: torch.nn.functional.conv2d(torch.nn.functional.pad(z, (5, 5, 5, 5), mode="reflect"), k)[..., 5:-5, 5:-5]
    mx, my = f(X), f(Y)
    vx, vy, cxy = f(X * X) - mx ** 2, f(Y * Y) - my ** 2, f(X * Y) - mx * my
    c1, c2 = (0.01 * r) ** 2, (0.03 * r) ** 2
    s = (2 * mx * my + c1) * (2 * cxy + c2) / ((mx ** 2 + my ** 2 + c1) * (vx + vy + c2))
    return float(s.mean())


# ---------------------------------------------------------------- PSNR / MAE

def test_psnr_of_known_mse():
    gt = np.zeros((8, 9))
    assert psnr(gt + 0.1, gt, 2.0) == pytest.approx(10 * math.log10(4 / 0.01), abs=1e-9)
    pred = gt.copy()
    pred[0, 0] = 3.0                       # MSE = 9 / 72 = 0.125
    assert psnr(pred, gt, 1.0) == pytest.approx(10 * math.log10(1 / 0.125), abs=1e-9)
    assert mae(pred, gt) == pytest.approx(3 / 72)


def test_psnr_identical_is_capped_and_bad_range_rejected():
    a = np.ones((4, 4))
    assert psnr(a, a, 2.0) == PSNR_CAP_DB
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(InputError):
            psnr(a, a, bad)
    with pytest.raises(InputError):
        psnr(a, a * np.nan, 1.0)
    with pytest.raises(InputError):
        mae(np.ones(3), np.ones(4))


# ---------------------------------------------------------------- SSIM

def test_ssim_identical_is_one_and_symmetric(rng):
    x = rng.normal(size=(20, 24))
    y = x + 0.3 * rng.normal(size=x.shape)
    assert ssim(x, x, 4.0) == pytest.approx(1.0, abs=1e-12)
    s = ssim(x, y, 4.0)
    assert s < 1.0
    assert s == pytest.approx(ssim(y, x, 4.0), abs=1e-12)
    assert ssim(x, -x, 4.0) < s


def test_ssim_constant_images_hand_computed():
    a, b, r = 0.3, 0.5, 1.0
    c1 = (0.01 * r) ** 2
    expected = (2 * a * b + c1) / (a * a + b * b + c1)      # variances are 0: contrast term 1
    assert ssim(np.full((12, 12), a), np.full((12, 12), b), r) == pytest.approx(expected, rel=1e-9)


def test_ssim_matches_direct_loop_and_torch_reference(rng):
    x = rng.normal(size=(16, 19))
    y = 0.7 * x + 0.4 * rng.normal(size=x.shape) + 0.1
    r = 2 * np.abs(y).max()
    got = ssim(x, y, r)
    assert got == pytest.approx(_ssim_loop(x, y, r), abs=1e-10)
    assert got == pytest.approx(_ssim_torch(x, y, r), abs=1e-10)
    # a stack is the mean of its images
    stack = ssim(np.stack([x, y]), np.stack([y, y]), r)
    assert stack == pytest.approx((got + 1.0) / 2, abs=1e-10)


def test_ssim_small_images_and_extreme_values(rng):
    x = rng.normal(size=(5, 7))
    assert ssim(x, x, 1.0) == pytest.approx(1.0)
    assert np.isfinite(ssim(x, x + 0.1, 1.0))
    big = 1e6 + rng.normal(size=(16, 16))
    s = ssim(big, big, 1.0)
    assert np.isfinite(s) and s == pytest.approx(1.0, abs=1e-9)
    assert np.isfinite(ssim(big, -big, 4e6))


# ---------------------------------------------------------------- quantisation

def test_quantize_matches_floor_counts(rng):
    d = rng.normal(scale=1.0, size=(30, 30))
    c_pos, c_neg = 0.2, 0.35
    q = quantize_log_change(d, c_pos, c_neg)
    n = counts_from_log_change(d, c_pos, c_neg)
    expected = np.where(n > 0, n * c_pos, n * c_neg)
    np.testing.assert_allclose(q, expected, atol=1e-12)
    assert np.all(np.abs(q) <= np.abs(d) + 1e-12)
    assert np.all(q * d >= 0)
    np.testing.assert_allclose(quantize_log_change([0.59, -0.69, 0.1], 0.2, 0.35),
                               [0.4, -0.35, 0.0], atol=1e-12)
    with pytest.raises(InputError):
        quantize_log_change(d, 0.0, 0.2)


# ---------------------------------------------------------------- event_metrics

def _event_stack(rng, k=5, h=16, w=16, c=0.2):
    n = rng.integers(-3, 4, size=(k, h, w)) * (rng.random((k, h, w)) < 0.1)
    return n * c


def test_event_metrics_floor_and_default_range(rng):
    gt = _event_stack(rng)
    pred = gt + rng.normal(scale=0.05, size=gt.shape)
    m = event_metrics(pred, gt, c_pos=0.2, c_neg=0.2)
    r = 2 * np.abs(gt).max()
    assert m["data_range"] == pytest.approx(r) and m["data_range_source"] == "2*max|gt|"
    floor = np.mean([psnr(np.zeros_like(g), g, r) for g in gt])
    assert m["zero_floor"]["psnr"] == pytest.approx(floor)
    assert m["zero_floor"]["psnr_pooled"] == pytest.approx(psnr(np.zeros_like(gt), gt, r))
    assert m["continuous"]["psnr"] > m["zero_floor"]["psnr"]
    assert m["continuous"]["psnr"] == pytest.approx(np.mean([psnr(p, g, r) for p, g in zip(pred, gt)]))
    assert m["continuous"]["mae"] == pytest.approx(mae(pred, gt))
    assert m["continuous"]["ssim"] == pytest.approx(ssim(pred, gt, r))
    q = quantize_log_change(pred, 0.2, 0.2)
    assert m["quantized"]["mae"] == pytest.approx(mae(q, gt))
    assert m["lpips"] is None and m["n_windows"] == 5
    given = event_metrics(pred, gt, c_pos=0.2, c_neg=0.2, data_range=10.0)
    assert given["data_range"] == 10.0 and given["data_range_source"] == "given"
    # exact prediction of event images: quantisation is lossless, PSNR capped, SSIM 1
    exact = event_metrics(gt, gt, c_pos=0.2, c_neg=0.2)
    assert exact["quantized"]["psnr"] == PSNR_CAP_DB and exact["quantized"]["ssim"] == pytest.approx(1.0)


def _all_finite(d):
    if isinstance(d, dict):
        return all(_all_finite(v) for v in d.values())
    if isinstance(d, list):
        return all(_all_finite(v) for v in d)
    if isinstance(d, float):
        return math.isfinite(d)
    return True


def test_event_metrics_never_nan(rng):
    zero = np.zeros((3, 12, 12))
    m = event_metrics(zero, zero, c_pos=0.01, c_neg=2.0)       # no events anywhere
    assert _all_finite(m) and m["data_range"] == 4.0
    assert m["continuous"]["psnr"] == PSNR_CAP_DB == m["zero_floor"]["psnr"]
    noisy = rng.normal(size=zero.shape)
    assert _all_finite(event_metrics(noisy, zero, c_pos=0.01, c_neg=2.0))
    gt = _event_stack(rng, k=4)
    gt[1] = 0.0                                                  # a window with no events
    assert _all_finite(event_metrics(gt + 0.01, gt, c_pos=0.2, c_neg=0.2))
    huge = 1e6 * np.sign(rng.normal(size=(2, 12, 12)))
    m = event_metrics(-huge, huge, c_pos=0.01, c_neg=0.01)
    assert _all_finite(m) and m["continuous"]["psnr"] < m["zero_floor"]["psnr"]
    tiny_c = event_metrics(gt * 1e3, gt, c_pos=1e-9, c_neg=1e-9)  # ~1e11 quantisation levels
    assert _all_finite(tiny_c)
    with pytest.raises(InputError):
        event_metrics(np.zeros((0, 4, 4)), np.zeros((0, 4, 4)), c_pos=0.2, c_neg=0.2)
    with pytest.raises(InputError):
        event_metrics(zero * np.nan, zero, c_pos=0.2, c_neg=0.2)


# ---------------------------------------------------------------- protocol, alignment

def test_protocol_windows():
    assert protocol_windows(10).tolist() == [0, 4, 8]
    assert protocol_windows(9).tolist() == [0, 4]        # window 8 is the last: skipped
    assert protocol_windows(5).tolist() == [0]
    assert protocol_windows(1).tolist() == [] and protocol_windows(0).tolist() == []
    assert protocol_windows(32).tolist() == [0, 4, 8, 12, 16, 20, 24, 28]
    with pytest.raises(InputError):
        protocol_windows(-1)


def test_brightness_align(rng):
    gt = rng.random((10, 10)) + 0.1
    aligned, a, b = brightness_align(3.0 * gt - 0.5, gt)
    assert a == pytest.approx(1 / 3) and b == pytest.approx(0.5 / 3)
    np.testing.assert_allclose(aligned, gt, atol=1e-12)
    aligned, a, b = brightness_align(2.0 * gt ** 1.5, gt, space="log", eps=0.0 + 1e-300)
    np.testing.assert_allclose(aligned, gt, rtol=1e-9)
    flat, a, b = brightness_align(np.full_like(gt, 7.0), gt)
    assert a == 1.0 and np.allclose(flat, gt.mean())
    with pytest.raises(InputError):
        brightness_align(gt, gt, space="gamma")


# ---------------------------------------------------------------- figures and report

def _write_run(path, label, rows, extra_lines=()):
    path.mkdir()
    with open(path / "metrics.jsonl", "w") as f:
        for it, wall, p, floor in rows:
            f.write(json.dumps({"iter": it, "wall_s": wall, "val_psnr": p,
                                "val_psnr_zero_floor": floor, "label": label}) + "\n")
        for line in extra_lines:
            f.write(line + "\n")


def test_side_by_side_png(tmp_path, rng):
    gt = _event_stack(rng, k=10)
    out = side_by_side(gt, gt * 0.5, tmp_path / "sbs.png", max_windows=4)
    assert out.read_bytes()[:8] == PNG_MAGIC
    side_by_side(np.zeros((1, 8, 8)), np.zeros((1, 8, 8)), tmp_path / "zero.png")
    assert (tmp_path / "zero.png").read_bytes()[:8] == PNG_MAGIC
    with pytest.raises(InputError):
        side_by_side(gt, gt[:2], tmp_path / "bad.png")


def test_report_from_two_runs(tmp_path):
    _write_run(tmp_path / "a", "planes", [(0, 0.0, 20.0, 19.5), (100, 30.0, 25.0, 19.5),
                                          (200, 61.5, 24.0, 19.5)],
               extra_lines=["", json.dumps({"iter": 150, "wall_s": 45.0, "loss": 0.1})])
    _write_run(tmp_path / "b", "dnerf", [(0, 0.0, 19.0, 19.5), (10, 60.0, 21.0, 19.5)])
    res = run_report([tmp_path / "a", tmp_path / "b"], tmp_path / "rep")
    assert (tmp_path / "rep" / "report.png").read_bytes()[:8] == PNG_MAGIC
    md = (tmp_path / "rep" / "report.md").read_text()
    assert "| planes | 200 | 61.5 | 25.00 | 24.00 | 19.50 | – | – |" in md
    assert "| dnerf | 10 | 60.0 | 21.00 | 21.00 | 19.50 | – | – |" in md
    assert [r["run"] for r in res["runs"]] == ["planes", "dnerf"]
    assert markdown_table([tmp_path / "b"]).count("\n") == 3
    plot_runs([tmp_path / "a"], tmp_path / "one.png")
    assert (tmp_path / "one.png").read_bytes()[:8] == PNG_MAGIC
    assert read_metrics(tmp_path / "a")["iter"].tolist() == [0, 100, 200]
    assert not list((tmp_path / "rep").glob(".*partial*"))


def test_report_with_the_true_scene(tmp_path):
    """Runs on a simulated set log the true scene's score and the margin closed (null: no margin)."""
    run = tmp_path / "t"
    run.mkdir()
    lines = [{"iter": 10, "wall_s": 5.0, "val_psnr": 31.0, "val_psnr_zero_floor": 30.0, "val_psnr_truth": 40.0,
              "val_margin_closed": 0.1},
             {"iter": 20, "wall_s": 9.0, "val_psnr": 36.0, "val_psnr_zero_floor": 30.0, "val_psnr_truth": 40.0,
              "val_margin_closed": 0.6}]
    (run / "metrics.jsonl").write_text("\n".join(json.dumps(x) for x in lines) + "\n")
    res = run_report([run], tmp_path / "rep")
    assert "| t | 20 | 9.0 | 36.00 | 36.00 | 30.00 | 40.00 | 60 % | – |" in (tmp_path / "rep" / "report.md").read_text()
    assert res["runs"][0]["margin_closed"] == pytest.approx(0.6)
    # a sparse set: no margin by the mean over windows, one pooled
    lines[1].update(val_margin_closed=None, val_margin_closed_pooled=0.25)
    (run / "metrics.jsonl").write_text("\n".join(json.dumps(x) for x in lines) + "\n")
    res = run_report([run], tmp_path / "rep", overwrite=True)
    assert "| 40.00 | – | 25 % |" in (tmp_path / "rep" / "report.md").read_text()
    assert res["runs"][0]["margin_closed_pooled"] == pytest.approx(0.25)
    del lines[1]["val_margin_closed_pooled"]
    lines[1]["val_margin_closed"] = 0.6
    lines[1]["val_margin_closed"] = None
    (run / "metrics.jsonl").write_text("\n".join(json.dumps(x) for x in lines) + "\n")
    assert read_metrics(run)["margin"][1] != read_metrics(run)["margin"][1]       # NaN: no margin
    assert run_report([run], tmp_path / "rep", overwrite=True)["runs"][0]["margin_closed"] is None


@pytest.mark.parametrize("line, msg", [
    ("{not json", "not valid JSON"),
    ("[1, 2]", "expected a JSON object"),
    ('{"iter": 5, "val_psnr": 20.0, "val_psnr_zero_floor": 1.0}', "'wall_s'"),
    ('{"iter": 5, "wall_s": 1.0, "val_psnr": 20.0}', "'val_psnr_zero_floor'"),
    ('{"iter": 5, "wall_s": 1.0, "val_psnr": NaN, "val_psnr_zero_floor": 1.0}', "finite"),
])
def test_report_bad_line_names_file_and_line(tmp_path, line, msg):
    _write_run(tmp_path / "r", "x", [(0, 0.0, 20.0, 19.0)], extra_lines=[line])
    with pytest.raises(InputError, match=msg) as exc:
        run_report([tmp_path / "r"], tmp_path / "out")
    assert "metrics.jsonl: line 2" in str(exc.value)
    assert not (tmp_path / "out" / "report.md").exists()


def test_report_missing_or_empty_metrics(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="metrics.jsonl: no such file"):
        markdown_table([tmp_path / "empty"])
    (tmp_path / "empty" / "metrics.jsonl").write_text('{"iter": 1, "wall_s": 2.0, "loss": 1}\n')
    with pytest.raises(InputError, match="no evaluation records"):
        plot_runs([tmp_path / "empty"], tmp_path / "x.png")
    with pytest.raises(InputError):
        run_report([], tmp_path / "out")
