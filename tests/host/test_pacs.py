"""``lamina send`` against a real PACS: Debian's Orthanc, started here on the loopback address.

Orthanc runs once for the module with a configuration written into a temporary folder (its
own storage and index, free DICOM and HTTP ports, no remote access, no authentication, the
called AE title checked, stores accepted only from Lamina's AE title on 127.0.0.1). The
stored instance is fetched back through Orthanc's REST API and compared with what
``lamina export`` writes for the same scan. The failures (refusals, nothing listening, a
socket that never answers, a C-STORE failure status, a bad ``--to``) each end in one line
and a non-zero exit, and leave the library's scans table and file bytes as they were.
"""

from __future__ import annotations

import io
import json
import shutil
import socket
import sqlite3
import subprocess
import time
import urllib.request
from collections.abc import Iterator
from contextlib import closing
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pydicom
import pytest

from lamina_host.cli import main
from lamina_host.reconstruct.mesh import load_ply
from lamina_host.store.dicom import ENCAPSULATED_STL, read_stl_triangles
from lamina_host.store.library import Library
from tests.helpers.cli import host_command

from .conftest import SUBJECT

ORTHANC = shutil.which("Orthanc")
NO_ORTHANC = (
    "Orthanc is not installed: apt-get install -y orthanc (the PACS lamina send is tested "
    "against); the tests that need no PACS still run"
)

PACS_AE = "LAMINATEST"
CALLING_AE = "LAMINA"
COMPARED = (
    "SOPClassUID", "PatientID", "PatientName", "StudyInstanceUID", "StudyDate", "StudyTime",
    "StudyID", "StudyDescription", "SeriesInstanceUID", "SeriesNumber", "SeriesDescription",
    "Modality", "FrameOfReferenceUID", "InstitutionName", "MIMETypeOfEncapsulatedDocument",
)  # fmt: skip
"""The patient, study and series attributes the stored instance must share with the export."""


@dataclass(frozen=True)
class Pacs:
    """A running Orthanc: its DICOM port and the base address of its REST API."""

    dicom_port: int
    http_url: str

    def get(self, path: str) -> bytes:
        """Return the body of a GET on the REST API."""
        with urllib.request.urlopen(self.http_url + path, timeout=10) as answer:
            return bytes(answer.read())

    def instance_file(self, sop_instance_uid: str) -> bytes:
        """Return the stored file of that SOP Instance UID, found through ``/instances``."""
        for orthanc_id in json.loads(self.get("/instances")):
            tags = json.loads(self.get(f"/instances/{orthanc_id}"))["MainDicomTags"]
            if tags["SOPInstanceUID"] == sop_instance_uid:
                return self.get(f"/instances/{orthanc_id}/file")
        raise AssertionError(f"Orthanc holds no instance {sop_instance_uid}")


def free_port() -> int:
    """Return a TCP port nothing listens on at the moment."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def orthanc_config(folder: Path, dicom_port: int, http_port: int) -> dict[str, Any]:
    """Return an Orthanc configuration of its own, on the loopback address only."""
    storage = folder / "storage"
    return {
        "Name": "lamina-test",
        "StorageDirectory": str(storage),
        "IndexDirectory": str(storage),
        "StorageCompression": False,
        "Plugins": [],
        "HttpPort": http_port,
        "RemoteAccessAllowed": False,
        "AuthenticationEnabled": False,
        "DicomAet": PACS_AE,
        "DicomPort": dicom_port,
        "DicomCheckCalledAet": True,
        # Stores only from Lamina's AE title on this machine (Orthanc 1.10 binds its DICOM
        # port on every interface; this keeps the test's PACS closed to anyone else).
        "DicomAlwaysAllowStore": False,
        "DicomCheckModalityHost": True,
        "DicomModalities": {"lamina": [CALLING_AE, "127.0.0.1", 104]},  # its port unused
        "AcceptedTransferSyntaxes": ["1.2.840.10008.1.2", "1.2.840.10008.1.2.1"],
        "DicomScpTimeout": 10,
    }


def _wait_for_http(process: subprocess.Popen[bytes], url: str, log: Path) -> None:
    deadline = time.monotonic() + 30.0
    while time.monotonic() < deadline:
        if process.poll() is not None:
            raise AssertionError(f"Orthanc stopped at start:\n{log.read_text()[-2000:]}")
        try:
            with urllib.request.urlopen(url + "/system", timeout=1):
                return
        except OSError:
            time.sleep(0.1)
    raise AssertionError(f"Orthanc did not answer on {url} within 30 s")


@pytest.fixture(scope="module")
def pacs(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Pacs]:
    """Start Orthanc for the module, on free ports, and stop it afterwards."""
    if ORTHANC is None:
        pytest.skip(NO_ORTHANC)
    folder = tmp_path_factory.mktemp("orthanc")
    dicom_port, http_port = free_port(), free_port()
    config = folder / "orthanc.json"
    config.write_text(json.dumps(orthanc_config(folder, dicom_port, http_port)))
    log = folder / "orthanc.log"
    with log.open("wb") as sink:
        process = subprocess.Popen([ORTHANC, str(config)], stdout=sink, stderr=subprocess.STDOUT)
    url = f"http://127.0.0.1:{http_port}"
    try:
        _wait_for_http(process, url, log)
        yield Pacs(dicom_port, url)
    finally:
        process.terminate()
        try:
            process.wait(timeout=20)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(timeout=10)


def lamina(*args: str, timeout_s: float = 120) -> subprocess.CompletedProcess[str]:
    """Run ``lamina`` in a fresh process."""
    return subprocess.run(host_command(*args), capture_output=True, text=True, timeout=timeout_s)


def library_state(library: Path) -> tuple[list[tuple[Any, ...]], dict[str, bytes]]:
    """Return the library's scans table and the bytes of its files (database and sidecars)."""
    with closing(sqlite3.connect(f"file:{library}?mode=ro", uri=True)) as db:
        scans = db.execute("SELECT * FROM scans ORDER BY id").fetchall()
    files = {p.name: p.read_bytes() for p in sorted(library.parent.glob(library.name + "*"))}
    return scans, files


def send(library: Path, to: str, *options: str) -> subprocess.CompletedProcess[str]:
    """Run ``lamina send 1 --to TO`` on ``library``; the library must be unchanged after it."""
    before = library_state(library)
    done = lamina("send", "1", "--to", to, "--library", str(library), *options)
    after = library_state(library)
    assert after[0] == before[0], "lamina send changed the scans table"
    assert after[1] == before[1], "lamina send changed the library's files"
    return done


def refused(done: subprocess.CompletedProcess[str], *words: str) -> str:
    """Return the one line a failed send printed, checking its exit, shape and words."""
    assert done.returncode != 0, done.stdout
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("lamina: "), done.stderr
    assert "Traceback" not in done.stderr
    for word in words:
        assert word in lines[0], lines[0]
    return lines[0]


def test_send_stores_what_export_writes(pacs: Pacs, scanned_library: Path, tmp_path: Path) -> None:
    exported = tmp_path / "scan1.dcm"
    options = ("--institution", "Lamina Test Clinic")
    done = lamina("export", "1", "-o", str(exported), "--library", str(scanned_library), *options)
    assert done.returncode == 0, done.stderr
    done = send(scanned_library, f"{PACS_AE}@127.0.0.1:{pacs.dicom_port}", *options)
    assert done.returncode == 0, done.stderr
    uid = done.stdout.strip().rsplit(" ", 1)[-1]
    assert done.stdout.startswith(f"stored scan 1 in {PACS_AE}@127.0.0.1:"), done.stdout
    stored_file = pacs.instance_file(uid)
    stored = pydicom.dcmread(io.BytesIO(stored_file))
    written = pydicom.dcmread(exported)
    assert stored.SOPClassUID == ENCAPSULATED_STL
    for keyword in COMPARED:
        assert stored[keyword].value == written[keyword].value, keyword
    assert stored.PatientID == SUBJECT and str(stored.PatientName) == ""
    stored_mesh = read_stl_triangles(stored_file)
    with Library(scanned_library) as library:
        vertices, faces = load_ply(library.result_mesh(1))
    assert len(faces) > 100
    assert np.array_equal(stored_mesh, read_stl_triangles(str(exported)))
    assert np.array_equal(stored_mesh, vertices[faces])


def test_a_wrong_called_ae_title_is_refused(pacs: Pacs, scanned_library: Path) -> None:
    done = send(scanned_library, f"NOTTHEPACS@127.0.0.1:{pacs.dicom_port}")
    refused(done, "refused the association", "'NOTTHEPACS'", f"'{CALLING_AE}'", "Called AE")


def test_a_calling_ae_title_the_pacs_does_not_know_is_refused(
    pacs: Pacs, scanned_library: Path
) -> None:
    done = send(
        scanned_library, f"{PACS_AE}@127.0.0.1:{pacs.dicom_port}", "--calling-ae", "STRANGER"
    )
    # Orthanc accepts the association, then ends it at the C-STORE (its DicomModalities).
    refused(done, "ended the association without storing", "'STRANGER'")


def test_nothing_listening_is_one_line(scanned_library: Path) -> None:
    refused(send(scanned_library, f"{PACS_AE}@127.0.0.1:{free_port()}"), "nothing accepts")


def test_a_socket_that_never_answers_times_out(scanned_library: Path) -> None:
    with socket.socket() as silent:  # the kernel accepts connections; nothing ever answers
        silent.bind(("127.0.0.1", 0))
        silent.listen(4)
        to = f"{PACS_AE}@127.0.0.1:{silent.getsockname()[1]}"
        started = time.monotonic()
        done = send(scanned_library, to, "--timeout-s", "1")
    refused(done, "did not answer the association within 1 s", "--timeout-s")
    assert time.monotonic() - started < 30


@pytest.mark.parametrize(
    "to",
    ["pacs.example.org:4242", "ORTHANC@pacs.example.org", "ORTHANC@:4242", "@127.0.0.1:4242",
     "ORTHANC@127.0.0.1:port", "ORTHANC@127.0.0.1:70000", "AN_AE_TITLE_TOO_LONG@127.0.0.1:4242",
     "ORTHANC@no-such-host.invalid:4242"],
)  # fmt: skip
def test_a_bad_to_says_the_form(
    scanned_library: Path, to: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """In this process (nothing is sent): one line naming --to and what to write."""
    before = library_state(scanned_library)
    status = main(["send", "1", "--to", to, "--library", str(scanned_library)])
    assert library_state(scanned_library) == before
    captured = capsys.readouterr()
    done = subprocess.CompletedProcess(["lamina"], status, captured.out, captured.err)
    line = refused(done, "--to")
    assert any(hint in line for hint in ("AE_TITLE@HOST:PORT", "port must be", "AE title", "host"))


@pytest.mark.parametrize(
    ("options", "needle"),
    [(("--calling-ae", ""), "--calling-ae: the AE title"),
     (("--calling-ae", "A\\B"), "--calling-ae: the AE title"),
     (("--timeout-s", "0"), "--timeout-s 0.0 must be"),
     (("--timeout-s", "nan"), "--timeout-s nan must be")],
)  # fmt: skip
def test_bad_send_options_are_one_line(
    scanned_library: Path, options: tuple[str, str], needle: str, capsys: pytest.CaptureFixture[str]
) -> None:
    before = library_state(scanned_library)
    argv = ["send", "1", "--to", f"{PACS_AE}@127.0.0.1:4242", "--library", str(scanned_library)]
    status = main([*argv, *options])
    assert library_state(scanned_library) == before
    captured = capsys.readouterr()
    refused(subprocess.CompletedProcess(["lamina"], status, captured.out, captured.err), needle)


def test_a_store_failure_status_is_given_in_hex(scanned_library: Path) -> None:
    """A PACS that answers the C-STORE with 0xA700 (out of resources): the code and meaning."""
    from pynetdicom import AE, evt

    scp = AE(ae_title=PACS_AE)
    scp.add_supported_context(ENCAPSULATED_STL, ["1.2.840.10008.1.2.1", "1.2.840.10008.1.2"])
    server = scp.start_server(
        ("127.0.0.1", 0), block=False, evt_handlers=[(evt.EVT_C_STORE, lambda event: 0xA700)]
    )
    try:
        port = server.server_address[1]
        done = send(scanned_library, f"{PACS_AE}@127.0.0.1:{port}")
    finally:
        server.shutdown()
    refused(done, "did not store the scan", "status 0xA700", "Refused: Out of Resources")
