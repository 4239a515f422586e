"""Words for people on the command line (issue #24 part 4): one line and what to do.

Each test first reproduces a problem the clinic's trial met: an option typo printed 15
lines of usage before its one line, with no "did you mean"; ``lamina scan --resume N`` of
a finished scan silently reprocessed it and rewrote its output folder.
"""

from __future__ import annotations

import shutil
import sqlite3
from pathlib import Path

import pytest

from lamina_host.cli import main
from lamina_host.store.library import Library


def refusal(capsys: pytest.CaptureFixture[str], *argv: str) -> str:
    """Run the command line, which must refuse with exit 2; return its one line."""
    try:
        status = main(list(argv))
    except SystemExit as exc:
        status = int(exc.code or 0)
    out, err = capsys.readouterr()
    assert status == 2 and out == ""
    assert err.count("\n") == 1 and "usage:" not in err, err
    return err.strip()


@pytest.mark.parametrize(
    ("argv", "words"),
    [
        (["scan", "--devce", "sim", "-o", "x"],
         "there is no option --devce; did you mean --device?"),
        (["scan", "--device", "sim", "--nosie", "harsh", "-o", "x"], "did you mean --noise?"),
        (["scan", "--device", "sim", "--noise", "harsch", "-o", "x"],
         "'harsch' is not a choice of --noise (choose from thesis, harsh, wide, none); did you "
         "mean harsh?"),
        (["scna", "--device", "sim"], "'scna' is no command"),
        (["report", "1", "-o", "x.pdf", "--compare-as", "visit"], "did you mean visits?"),
        (["scans", "--set-tset", "1"], "did you mean --set-test?"),
        (["scan", "--device", "sim", "--sections", "x", "-o", "x"], "--sections: invalid int"),
    ],
)  # fmt: skip
def test_an_option_typo_is_one_line_with_the_nearest_word(
    capsys: pytest.CaptureFixture[str], argv: list[str], words: str
) -> None:
    """One line naming the mistake and the nearest right word, never the whole usage."""
    line = refusal(capsys, *argv)
    assert words in line and line.startswith("lamina")


def test_a_device_name_typo_says_did_you_mean_before_anything_starts(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    """``--device simm`` (scan, tui) is named as a typo of ``sim``, before a library or an
    output folder is made; an abbreviation argparse accepts (``--dev``) still works."""
    library, out = tmp_path / "library.sqlite", tmp_path / "out"
    line = refusal(capsys, "scan", "--device", "simm", "-o", str(out), "--library", str(library))
    assert "--device simm" in line and "did you mean --device sim?" in line
    assert not out.exists()
    assert "did you mean --device local?" in refusal(capsys, "tui", "--device", "locl")
    assert "does not exist" in refusal(
        capsys,
        "scan",
        "--dev",
        str(tmp_path / "ttyACM9"),
        "-o",
        str(out),
        "--library",
        str(library),
    )


def dump(path: Path) -> list[tuple]:
    """Return every row of the library's scans, results and segments."""
    with sqlite3.connect(path) as db:
        return [
            tuple(row)
            for table in ("scans", "results", "result_files", "segments")
            for row in db.execute(f"SELECT * FROM {table} ORDER BY 1")
        ]


def test_resuming_a_finished_scan_says_so_and_writes_nothing_unless_asked(
    scanned_library: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Issue #24: ``--resume N`` of a finished scan reprocessed it and rewrote its folder.
    Now it says the scan is complete and how to see or reprocess it, and changes nothing;
    ``--reprocess`` processes it again (into the folder named)."""
    library = tmp_path / "library.sqlite"
    shutil.copyfile(scanned_library, library)
    before = dump(library)
    base = ["scan", "--device", "sim", "--resume", "1", "--library", str(library)]
    assert main(base) == 0
    out = capsys.readouterr().out
    assert out.strip() == (
        "scan 1 is complete (every view held, processed); nothing was written: see it with "
        "lamina report 1 -o FILE.pdf, or process it again with --reprocess"
    )
    assert dump(library) == before
    again = tmp_path / "again"
    assert main([*base, "--reprocess", "-o", str(again)]) == 0
    capsys.readouterr()
    assert (again / "report.json").is_file() and (again / "mesh.ply").is_file()
    with Library(library) as lib:
        (summary,) = lib.scans()
        assert summary.status == "processed" and summary.side == "left"
    line = refusal(capsys, "scan", "--device", "sim", "--reprocess", "-o", str(tmp_path / "new"),
                   "--library", str(library))  # fmt: skip
    assert "--reprocess applies to a scan resumed with --resume SCAN" in line
