"""`fitme batch`: manifests, resumability, failures that do not stop the batch, the Ray executor."""

import csv
import json

import pytest
from click.testing import CliRunner

from fitme_cli.batch.manifest import Subject, read_subjects, subject_key
from fitme_cli.cli import main
from fitme_cli.errors import InputNotFound, WrongLayout


def _photo(models_root, path):
    from fitme_cli.io.images import write_sample_photo

    return write_sample_photo("astronaut", path)


def test_subjects_from_folders_and_from_a_csv_manifest(tmp_path):
    (tmp_path / "in" / "bob").mkdir(parents=True)
    (tmp_path / "in" / "alice").mkdir()
    (tmp_path / "in" / "alice" / "b.jpg").write_bytes(b"x")
    (tmp_path / "in" / "alice" / "a.PNG").write_bytes(b"x")
    (tmp_path / "in" / "alice" / "notes.txt").write_text("not a photo")
    subs = read_subjects(tmp_path / "in")
    assert [s.name for s in subs] == ["alice", "bob"]
    assert [p.name for p in subs[0].photos] == ["a.PNG", "b.jpg"] and subs[1].photos == ()
    m = tmp_path / "m.csv"
    with open(m, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["subject", "photos", "preset", "iterations"])
        w.writerow(["carol", "in/alice/a.PNG;in/alice/b.jpg", "fast", "5"])
        w.writerow(["carol", "/abs/c.jpg", "", ""])
        w.writerow(["dave", "x.jpg", "", ""])
    subs = read_subjects(m)
    assert [s.name for s in subs] == ["carol", "dave"]
    assert subs[0].photos[0] == (tmp_path / "in" / "alice" / "a.PNG").resolve() and str(subs[0].photos[2]) == "/abs/c.jpg"
    assert subs[0].settings == {"preset": "fast", "iterations": "5"} and subs[1].settings == {}
    for text, what in (("name,photos\nx,y\n", "columns"), ("subject,photos\n../evil,a.jpg\n", "folder name"),
                       ("subject,photos\nA,a.jpg\na,b.jpg\n", "twice")):
        m.write_text(text)
        with pytest.raises(WrongLayout, match=what):
            read_subjects(m)
    with pytest.raises(InputNotFound):
        read_subjects(tmp_path / "missing")
    (tmp_path / "flat").mkdir()
    with pytest.raises(WrongLayout, match="no subject folders"):
        read_subjects(tmp_path / "flat")


def test_subject_key_follows_photo_contents_and_settings(tmp_path):
    p = tmp_path / "a.jpg"
    p.write_bytes(b"one")
    s = Subject("a", (p,))
    k = subject_key(s, {"preset": "fast"})
    assert k == subject_key(s, {"preset": "fast"}) and k != subject_key(s, {"preset": "default"})
    p.write_bytes(b"two")
    assert subject_key(s, {"preset": "fast"}) != k


@pytest.fixture(scope="module")
def batch_input(tmp_path_factory, models_root):
    root = tmp_path_factory.mktemp("batch")
    for name in ("alice", "bob"):
        (root / "in" / name).mkdir(parents=True)
        _photo(models_root, root / "in" / name / "portrait.jpg")
    (root / "in" / "carl").mkdir()
    (root / "in" / "carl" / "x.jpg").write_text("not an image")
    m = root / "manifest.csv"
    m.write_text("subject,photos,iterations\n" + "".join(f"{n},in/{n}/{'x' if n == 'carl' else 'portrait'}.jpg,2\n"
                                                           for n in ("alice", "bob", "carl")))
    return root


def test_batch_runs_in_parallel_survives_failures_and_resumes(batch_input, tmp_path):
    out = tmp_path / "out"
    args = ["batch", str(batch_input / "manifest.csv"), "-o", str(out), "--preset", "fast", "--workers", "2"]
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 1, r.output  # carl failed; the others finished
    st = {n: json.loads((out / n / "status.json").read_text()) for n in ("alice", "bob", "carl")}
    assert st["alice"]["status"] == st["bob"]["status"] == "done" and st["carl"]["status"] == "failed"
    assert "not an image" in st["carl"]["error"] and st["carl"]["exit_code"] == 13
    assert (out / "alice" / "avatar" / "avatar.json").is_file() and (out / "alice" / "thumb.png").is_file()
    assert st["alice"]["settings"]["iterations"] == "2" and 0 <= st["alice"]["identity"] <= 1
    rows = list(csv.DictReader((out / "summary.csv").read_text().splitlines()))
    assert {row["subject"]: row["status"] for row in rows} == {"alice": "done", "bob": "done", "carl": "failed"}
    html = (out / "summary.html").read_text()
    assert "alice/thumb.png" in html and "not an image" in html
    # a re-run does nothing: finished subjects and known failures are skipped
    before = (out / "alice" / "avatar" / "avatar.json").stat().st_mtime_ns
    r = CliRunner().invoke(main, args)
    assert "0 run now" in r.output
    assert (out / "alice" / "avatar" / "avatar.json").stat().st_mtime_ns == before
    rows = {row["subject"]: row["status"] for row in csv.DictReader((out / "summary.csv").read_text().splitlines())}
    assert rows == {"alice": "skipped-done", "bob": "skipped-done", "carl": "skipped-failed"}
    # a subject killed before its status.json was written: only it runs again; --retry-failed retries carl
    (out / "bob" / "status.json").unlink()
    assert (out / "bob" / ".fitme-batch").is_file()
    r = CliRunner().invoke(main, args + ["--retry-failed"])
    rows = {row["subject"]: row["status"] for row in csv.DictReader((out / "summary.csv").read_text().splitlines())}
    assert rows == {"alice": "skipped-done", "bob": "done", "carl": "failed"}
    assert not [p for p in out.iterdir() if p.name.startswith(".")]  # no work folders left


def test_batch_never_replaces_a_folder_it_did_not_write(batch_input, tmp_path):
    out = tmp_path / "out"
    (out / "alice").mkdir(parents=True)
    (out / "alice" / "notes.txt").write_text("mine")
    m = tmp_path / "one.csv"
    m.write_text(f"subject,photos,iterations\nalice,{batch_input / 'in' / 'alice' / 'portrait.jpg'},2\n")
    r = CliRunner().invoke(main, ["batch", str(m), "-o", str(out), "--preset", "fast"])
    assert r.exit_code == 1 and "not written by fitme batch" in (out / "summary.csv").read_text()
    assert (out / "alice" / "notes.txt").read_text() == "mine"


def test_batch_refuses_bad_arguments(batch_input, tmp_path):
    r = CliRunner().invoke(main, ["batch", str(batch_input / "in"), "-o", str(batch_input / "in" / "out")])
    assert r.exit_code == 17 and "inside the input" in r.output
    r = CliRunner().invoke(main, ["batch", str(batch_input / "in"), "-o", str(tmp_path / "o"), "--export", "fbx"])
    assert r.exit_code == 2 and "fbx" in r.output
    r = CliRunner().invoke(main, ["batch", str(tmp_path / "nothing"), "-o", str(tmp_path / "o")])
    assert r.exit_code == 10


def test_batch_on_a_local_ray_instance(batch_input, tmp_path):
    pytest.importorskip("ray")
    m = tmp_path / "one.csv"
    m.write_text(f"subject,photos,iterations\nalice,{batch_input / 'in' / 'alice' / 'portrait.jpg'},2\n")
    out = tmp_path / "out"
    r = CliRunner().invoke(main, ["batch", str(m), "-o", str(out), "--preset", "fast", "--executor", "ray", "--threads", "1",
                                  "--export", "glb"])
    assert r.exit_code == 0, r.output
    st = json.loads((out / "alice" / "status.json").read_text())
    assert st["status"] == "done" and st["executor"] == "ray"
    assert (out / "alice" / "avatar" / "params.safetensors").is_file() and (out / "alice" / "thumb.png").is_file()
    assert (out / "alice" / "export" / "head.glb").stat().st_size > 100_000  # the export came back from the task
