"""Issue #24, items 3 and 8: ``highlight -o DIR`` never replaces the user's own files there without
--overwrite (an interrupted run's own files are resumed), and query text that is not UTF-8 is refused
before any output, so nothing partial is left to block the re-run."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import torch

from _language_helpers import micro_bundle
from fourlegs_engine.commands.main import main
from fourlegs_engine.errors import InputError, OutputExistsError
from fourlegs_engine.fileio import OUTPUTS_MARKER, claim_outputs, output_group
from fourlegs_engine.validate import check_text

NOT_UTF8 = b"a ball \xff flying".decode("utf-8", "surrogateescape")  # what Python makes of such argv bytes


class _Stop(Exception):
    """Raised in place of the job's first real stage: everything before it has run."""


def _headless_run(monkeypatch, argv):
    from fourlegs_addon import headless
    from fourlegs_engine import pipeline
    from fourlegs_engine.commands.options import highlight_job_options

    def stop(*args, **kwargs):
        raise _Stop

    monkeypatch.setattr(pipeline, "open_scene", stop)
    args = headless.build_parser().parse_args(argv)
    return headless.run(highlight_job_options(args))


def test_highlight_refuses_to_replace_the_users_plan_and_plot(tmp_path, monkeypatch):
    out = tmp_path / "out"
    out.mkdir()
    (out / "plan.json").write_text('{"mine": true}')
    (out / "scores.png").write_bytes(b"my picture")
    with pytest.raises(OutputExistsError) as exc:
        _headless_run(monkeypatch, ["--demo", "ball", "-o", str(out)])
    assert "plan.json" in str(exc.value) and "scores.png" in str(exc.value)
    assert (out / "plan.json").read_text() == '{"mine": true}'
    assert (out / "scores.png").read_bytes() == b"my picture"
    with pytest.raises(_Stop):  # --overwrite: the job may replace them
        _headless_run(monkeypatch, ["--demo", "ball", "-o", str(out), "--overwrite"])


def test_an_interrupted_highlight_resumes_over_its_own_files(tmp_path, monkeypatch):
    out = tmp_path / "out"
    with pytest.raises(_Stop):  # a failure before the first output leaves nothing behind
        _headless_run(monkeypatch, ["--demo", "ball", "-o", str(out)])
    assert not out.exists()
    claim_outputs(out, [out / "plan.json", out / "scores.png"], overwrite=False)()  # the job's first write
    assert json.loads((out / OUTPUTS_MARKER).read_text())["outputs"] == ["plan.json", "scores.png"]
    (out / "plan.json").write_text("{}")          # what the interrupted run had written
    with pytest.raises(_Stop):
        _headless_run(monkeypatch, ["--demo", "ball", "-o", str(out)])


def test_highlight_refuses_non_utf8_query_before_writing(tmp_path, monkeypatch):
    out = tmp_path / "out"
    with pytest.raises(InputError, match="not valid UTF-8.*0xff"):
        _headless_run(monkeypatch, ["--demo", NOT_UTF8, "-o", str(out)])
    assert not out.exists() or not any(out.iterdir())


def test_claim_outputs_names_every_foreign_file_at_once(tmp_path):
    for name in ("a.json", "b.png"):
        (tmp_path / name).write_text("x")
    outputs = [tmp_path / "a.json", tmp_path / "b.png", tmp_path / "c.txt"]
    with pytest.raises(OutputExistsError, match="a.json.*b.png"):
        claim_outputs(tmp_path, outputs, overwrite=False)
    record = claim_outputs(tmp_path, outputs, overwrite=True)
    assert not (tmp_path / OUTPUTS_MARKER).exists()   # nothing written before the command's first output
    record()
    claim_outputs(tmp_path, outputs, overwrite=False)  # now they are the command's own


def test_output_group_removes_what_it_wrote_when_a_later_output_fails(tmp_path):
    first = tmp_path / "first.json"
    with pytest.raises(UnicodeEncodeError):
        with output_group() as written:
            written.append(first)
            first.write_text("{}")
            NOT_UTF8.encode("utf-8")
    assert not first.exists()


@pytest.mark.parametrize("text", [NOT_UTF8, "\udcff", "x\ud800"])
def test_check_text_refuses_lone_surrogates(text):
    with pytest.raises(InputError, match="not valid UTF-8"):
        check_text(text, "text")
    assert check_text("ballon à la main ⚽", "text") == "ballon à la main ⚽"


@pytest.fixture(scope="module")
def distilled(tmp_path_factory) -> Path:
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    path = micro_bundle(tmp_path_factory.mktemp("outputs") / "micro", T=3)
    assert main(["extract", str(path), "--no-progress"]) == 0
    assert main(["train-ae", str(path), "--epochs", "1", "--samples", "1024", "--ae-batch-size", "256"]) == 0
    assert main(["distill", str(path), "--no-progress"]) == 0
    torch.set_num_threads(old)
    return path


def test_query_with_non_utf8_text_writes_nothing_and_the_rerun_works(distilled, tmp_path, capsys):
    out = tmp_path / "q.json"
    code = main(["query", str(distilled), NOT_UTF8, "--no-spatial", "--json", str(out)])
    err = capsys.readouterr().err
    assert code == 2 and "not valid UTF-8" in err and "Traceback" not in err
    assert list(tmp_path.iterdir()) == []
    assert main(["query", str(distilled), "a ball flying", "--no-spatial", "--json", str(out)]) == 0
    assert out.is_file() and out.with_suffix(".st.png").is_file()


def test_a_query_whose_plot_fails_leaves_no_json(distilled, tmp_path, capsys, monkeypatch):
    import errno

    import fourlegs_engine.query.plots as plots

    def full_disk(*a, **kw):
        raise OSError(errno.ENOSPC, "No space left on device", str(tmp_path / "q.st.png"))

    monkeypatch.setattr(plots, "plot_temporal", full_disk)
    out = tmp_path / "q.json"
    assert main(["query", str(distilled), "a ball flying", "--no-spatial", "--json", str(out)]) == 1
    assert "no space left on device while writing" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_plan_refuses_non_utf8_query_before_any_work(tmp_path, capsys):
    assert main(["plan", "--demo", NOT_UTF8, "-o", str(tmp_path / "plan.json")]) == 2
    assert "query: is not valid UTF-8" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("frame, message", [("999", "timestep 999 is out of range 0..2"),
                                            ("-1", "timestep -1 is out of range 0..2"),
                                            ("soon", "'soon' is neither a timestep nor 'peak'")])
def test_query_frames_out_of_range_say_so_and_write_nothing(distilled, tmp_path, capsys, frame, message):
    argv = ["query", str(distilled), "a ball flying", "--exr", str(tmp_path / "maps"), "--frames", frame,
            "--json", str(tmp_path / "q.json")]
    assert main(argv) == 2
    assert capsys.readouterr().err.strip().endswith(f"--frames: {message}")
    assert list(tmp_path.iterdir()) == []
