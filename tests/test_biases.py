"""Prophesee .bias files (rig.camera.biases) and the IMX636 bias table."""

from __future__ import annotations

import warnings

import pytest

from evdnerf_ros.errors import InputError, OutputExistsError
from rig.camera import evk4_registers as R
from rig.camera.biases import (
    BiasFileError, BiasRange, check_biases, format_biases, parse_biases, read_bias_file,
    write_bias_file,
)
from rig.camera.errors import CameraError

# a Metavision-style file: header lines, padding, an old-style trailing '% v' column
METAVISION_TEXT = """% characterization release 1.4
% gen 4.1 CD standard biases

0     % bias_diff
-12   % bias_diff_off   %   v
  25  % bias_diff_on
10    % bias_fo
0x10  % bias_hpf
# a comment
-5    % bias_refr
"""


def test_parse_metavision_style_file():
    b = parse_biases(METAVISION_TEXT, "cam.bias")
    assert b == {"bias_diff": 0, "bias_diff_off": -12, "bias_diff_on": 25, "bias_fo": 10,
                 "bias_hpf": 16, "bias_refr": -5}
    assert list(b) == ["bias_diff", "bias_diff_off", "bias_diff_on", "bias_fo", "bias_hpf",
                       "bias_refr"]


def test_round_trip_through_a_file(tmp_path):
    b = {"bias_diff_on": 30, "bias_diff_off": -20, "bias_fo": 5, "bias_hpf": 0, "bias_refr": 12,
         "bias_diff": -3}
    p = write_bias_file(tmp_path / "a.bias", b, header="EVK4 test\nsecond line")
    text = p.read_text()
    assert text.startswith("% EVK4 test\n% second line\n")
    assert "30    % bias_diff_on" in text
    assert read_bias_file(p, ranges=R.BIAS_RANGES) == b
    # no temp files left behind
    assert sorted(x.name for x in tmp_path.iterdir()) == ["a.bias"]


def test_write_refuses_to_overwrite(tmp_path):
    p = tmp_path / "a.bias"
    write_bias_file(p, {"bias_fo": 1})
    with pytest.raises(OutputExistsError):
        write_bias_file(p, {"bias_fo": 2})
    write_bias_file(p, {"bias_fo": 2}, overwrite=True)
    assert read_bias_file(p) == {"bias_fo": 2}


@pytest.mark.parametrize("text, line, words", [
    ("0 % bias_fo\nabc % bias_hpf\n", 2, "not an integer"),
    ("0 % bias_fo\n\n12 bias_hpf\n", 3, "expected '<value> % <bias name>'"),
    ("0 % bias_fo\n1 %   \n", 2, "missing or malformed bias name"),
    ("0 % bias_fo\n1 % bias fo\n", 2, "missing or malformed bias name"),
    ("0 % bias_fo\n% header\n1 % bias_fo\n", 3, "set twice (first on line 1)"),
    ("1.5 % bias_fo\n", 1, "not an integer"),
])
def test_syntax_errors_name_file_and_line(tmp_path, text, line, words):
    p = tmp_path / "bad.bias"
    p.write_text(text)
    with pytest.raises(BiasFileError) as ei:
        read_bias_file(p)
    msg = str(ei.value)
    assert f"{p}:{line}:" in msg and words in msg
    assert "\n" not in msg
    assert isinstance(ei.value, InputError) and isinstance(ei.value, CameraError)


def test_unknown_name_and_range_name_the_line(tmp_path):
    p = tmp_path / "x.bias"
    p.write_text("% hdr\n0 % bias_fo\n3 % bias_pr\n")
    with pytest.raises(BiasFileError, match=rf"{p}:3: unknown bias 'bias_pr'; valid biases: "
                                            r"bias_diff, bias_diff_off, bias_diff_on, bias_fo"):
        read_bias_file(p, ranges=R.BIAS_RANGES)
    p.write_text("0 % bias_fo\n\n201 % bias_diff_on\n")
    with pytest.raises(BiasFileError, match=rf"{p}:3: bias bias_diff_on = 201 is outside its "
                                            r"allowed range \[-150, 200\]"):
        read_bias_file(p, ranges=R.BIAS_RANGES)


def test_missing_empty_and_binary_files(tmp_path):
    with pytest.raises(BiasFileError, match="not found"):
        read_bias_file(tmp_path / "nope.bias")
    (tmp_path / "empty.bias").write_text("% only a header\n\n")
    with pytest.raises(BiasFileError, match="no bias lines"):
        read_bias_file(tmp_path / "empty.bias")
    (tmp_path / "bin.bias").write_bytes(b"\xff\xfe\x00 % bias_fo\n")
    with pytest.raises(BiasFileError, match="not UTF-8"):
        read_bias_file(tmp_path / "bin.bias")
    with pytest.raises(BiasFileError, match="is a directory"):
        read_bias_file(tmp_path)


def test_recommended_range_only_warns():
    with pytest.warns(UserWarning, match=r"outside the recommended range \[-85, 140\]"):
        assert check_biases({"bias_diff_on": 150}, R.BIAS_RANGES) == {"bias_diff_on": 150}
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_biases({"bias_diff_on": 140, "bias_hpf": 0}, R.BIAS_RANGES)
    with pytest.raises(BiasFileError, match="not an integer"):
        check_biases({"bias_fo": 1.5}, R.BIAS_RANGES)
    with pytest.raises(BiasFileError, match="not an integer"):
        check_biases({"bias_fo": True}, R.BIAS_RANGES)


def test_format_rejects_bad_names_and_values():
    with pytest.raises(BiasFileError, match="cannot be written"):
        format_biases({"bias fo": 1})
    with pytest.raises(BiasFileError, match="not an integer"):
        format_biases({"bias_fo": "1"})


def test_imx636_table_matches_openeb():
    """Names, register addresses and ranges (OpenEB imx636_bias_settings*.h)."""
    assert set(R.BIASES) == {"bias_fo", "bias_hpf", "bias_diff_on", "bias_diff", "bias_diff_off",
                             "bias_refr"}
    assert {n: s.address for n, s in R.BIASES.items()} == {
        "bias_fo": 0x1004, "bias_hpf": 0x100C, "bias_diff_on": 0x1010, "bias_diff": 0x1014,
        "bias_diff_off": 0x1018, "bias_refr": 0x1020}
    assert R.BIAS_RANGES["bias_refr"] == BiasRange(-50, 255, -20, 235)
    assert R.bias_register_value(0x4D) == 0x11A1004D
    assert R.bias_register_value(255) == 0x11A100FF and R.bias_register_value(0) == 0x11A10000
    for outside in (300, -4):                   # refused, never clamped (EVK4.set_biases checks first)
        with pytest.raises(ValueError, match="outside 0..255"):
            R.bias_register_value(outside)


def test_evk4_register_sequences_pin_the_source_values():
    """Spot values of the bring-up data (neuromorphic-drivers' prophesee_evk4.rs, OpenEB's
    imx636 issd / gen41 ROI), so an edit of the data cannot pass unnoticed."""
    assert R.roi_ctrl(rstn=False) == 0xF0005042 and R.roi_ctrl(rstn=True) == 0xF0005442
    assert R.roi_ctrl(rstn=True, shadow=True) == 0xF0005462
    assert [(w.address, w.value) for w in R.START] == [
        (0xB000, 0x2F9), (0x9028, 0x0), (0x9008, 0x645), (0x002C, 0x0022C724), (0x0004, 0xF0005442)]
    assert [(w.address, w.value) for w in R.STOP] == [
        (0x0004, 0xF0005042), (0x002C, 0x0022C324), (0x9028, 0x2), (0x9008, 0x644), (0xB000, 0x2F8)]
    init = [(w.address, w.value, w.delay_s) for w in R.INIT]
    assert init[:4] == [(0x001C, 1, 0.0), (0x400004, 1, 1.0), (0x400004, 0, 0.5), (0xB000, 0x158, 1.0)]
    assert init[-3:] == [(0x1014, 0x11A1504D, 0.0), (0x9004, 0, 0.001), (0x9000, 0x200, 0.0)]
    assert len(R.DESTROY) == 20 and len(R.INIT) == 67 and len(R.FILTERS) == 8
    assert len(R.ERC) == 4 + 230 + 1 + 256 + 4
    assert R.ERC[4 + 230 + 1 + 5] == R.Write(0x6414, (11 << 16) | 10)
    assert R.edf_7004(True) == 0xC5FF and R.edf_7004(False) == 0xC1FF
    seq = R.open_sequence()
    assert seq[-1] == R.Write(0x7004, 0xC1FF) and len(seq) == 5 + 20 + 67 + 8 + 495 + 1
    # ROI: complement masks, the last y register's top half forced to 1
    roi = R.roi_registers(32, 0, 32, 720)
    assert roi[0].value == 0xFFFFFFFF and roi[1].value == 0 and roi[2].value == 0xFFFFFFFF
    assert roi[40 + 22].value == 0xFFFF0000 and roi[-1].address == R.ROI_CTRL
    assert R.roi_from_registers([w.value for w in roi[:40]], [w.value for w in roi[40:63]]) == \
        (32, 0, 32, 720)
    with pytest.raises(ValueError, match="contiguous"):
        R.roi_from_registers([0b10] + [0] * 39, [0] * 23)
    assert R.write_command(0x9028, 2).hex() == "020101400c000000000000002890000002000000"
    assert R.read_command(0x1010).hex() == "020101000c000000000000001010000001000000"
