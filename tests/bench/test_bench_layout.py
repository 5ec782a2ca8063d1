"""bench.layout: its report table, and the ablation model's own cache name."""

from bench.layout import markdown
from bench.models import model_filename


def _row(scene, target, before, after, copy):
    return {"scene": scene, "references": ["a", "b"], "target": target, "copy_psnr": copy,
            "before": {"psnr": before, "ws_psnr": before - 1, "covered": 0.99},
            "after": {"psnr": after, "ws_psnr": after - 1, "covered": 0.98}}


def test_markdown_reports_change_and_means():
    res = {"machine": {"cpu_model": "cpu", "usable_cores": 2, "logical_cores": 2, "platform": "os", "python": "3",
                       "numpy": "2", "onnxruntime": "1", "load_average_1_5_15min": [0, 0, 0], "timestamp_utc": "t"},
           "rows": [_row("s", "t1", 16.0, 19.5, 17.0), _row("s", "t2", 15.0, 15.5, 14.0)],
           "seconds": [{"scene": "s", "references": ["a", "b"], "before": 1.25, "after": 1.5}],
           "figure": "x/layout.png"}
    text = markdown(res, "docs/bench/layout.png")
    assert "| s | a + b | t1 | 16.00 / 15.00 | 19.50 / 18.50 | +3.50 | 17.00 | 0.990 / 0.980 |" in text
    assert "mean PSNR of 2 targets 15.50 -> 17.50 dB (copy 15.50)" in text
    assert "1.25 s before, 1.50 s after" in text
    assert text.endswith("](docs/bench/layout.png)")


def test_ablation_model_has_its_own_file():
    on, off = model_filename(512, 1024, 64, False), model_filename(512, 1024, 64, False, layout=False)
    assert on != off and "_nolayout_" in off and "_nolayout" not in on
