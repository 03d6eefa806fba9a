"""d2turb.data.check: check-dataset on damaged dataset files."""

import json

from hostile_input import one_error_line, run_cli


def test_check_dataset_with_null_bin_ranges(tmp_path, capsys):
    (tmp_path / "dataset.json").write_text(json.dumps({"pairs": 1, "patch": 16, "bin_ranges": None}))
    rc, _, err = run_cli(capsys, ["check-dataset", str(tmp_path)])
    assert rc == 2
    one_error_line(err, "dataset.json", "bin_ranges")
