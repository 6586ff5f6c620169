"""The web API: bad uploads refused with one-line messages, a job end to end, limits, cleanup."""

import io
import threading
import time
import zipfile

import numpy as np
import pytest
from fastapi.testclient import TestClient
from PIL import Image

from pis3r.web.app import WebLimits, create_app
from pis3r.web.jobs import Job, JobQueue, ServerBusyError

LIMITS = WebLimits(max_file_bytes=200_000, max_pixels=100_000)


def png(array) -> bytes:
    buffer = io.BytesIO()
    Image.fromarray(array).save(buffer, format="PNG")
    return buffer.getvalue()


@pytest.fixture()
def client():
    with TestClient(create_app(LIMITS)) as client:
        yield client


def post(client, files, **form):
    return client.post("/api/jobs", files=[("files", f) for f in files], data=form)


def wait(client, job_id, timeout=120):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        job = client.get(f"/api/jobs/{job_id}").json()
        if job["status"] in ("done", "failed"):
            return job
        time.sleep(0.2)
    raise AssertionError("job did not finish")


@pytest.mark.parametrize("files, code, message", [
    ([("a.png", b"hello, not an image", "image/png"), ("b.txt", b"also not", "text/plain")], 400,
     "a.png: not an image"),
    ([("big.png", b"x" * 300_000, "image/png"), ("b.png", b"x", "image/png")], 413, "big.png: larger than"),
    ([("only.png", b"x", "image/png")], 400, "need at least 2 photos"),
    ([("../../etc/passwd", b"root:x:0:0", "text/plain"), ("b.png", b"x", "image/png")], 400, "passwd: not an image"),
    ([("empty.png", b"", "image/png"), ("b.png", b"x", "image/png")], 400, "empty.png: file is empty"),
])
def test_bad_uploads_get_one_line_messages(client, files, code, message):
    response = post(client, files)
    assert response.status_code == code
    detail = response.json()["detail"]
    assert message in detail and "\n" not in detail and "/etc" not in detail


def test_too_many_pixels_and_bad_reference(client, small_pair):
    huge = np.zeros((400, 400, 3), np.uint8)
    response = post(client, [("huge.png", png(huge), "image/png"), ("b.png", png(small_pair[1]), "image/png")])
    assert response.status_code == 413 and "megapixels" in response.json()["detail"]
    files = [(f"{i}.png", png(a), "image/png") for i, a in enumerate(small_pair)]
    response = post(client, files, ref="5")
    assert response.status_code == 400 and "reference" in response.json()["detail"]


def test_a_job_end_to_end_with_a_path_like_name(small_pair):
    app = create_app(LIMITS)
    root = app.state.jobs.root
    with TestClient(app) as client:
        files = [("../../etc/passwd", png(small_pair[0]), "image/png"), ("b c.png", png(small_pair[1]), "image/png")]
        response = post(client, files, backend="classical", matcher="sift", blend="multiband")
        assert response.status_code == 202, response.text
        job = wait(client, response.json()["id"])
        assert job["status"] == "done", job
        [confidence] = job["result"]["pose_confidence"]
        assert confidence["index"] == 1 and confidence["rotation_uncertainty_deg"] >= 0
        assert job["inputs"] == ["passwd", "b_c.png"]
        stored = sorted(p.relative_to(root).parts for p in root.rglob("*passwd"))
        assert stored == [(job["id"], "00_passwd")]
        assert job["result"]["parallax"]["label"]
        image = client.get(job["result"]["files"]["stitched.png"])
        assert image.status_code == 200 and image.content.startswith(b"\x89PNG")
        with zipfile.ZipFile(io.BytesIO(client.get(job["result"]["files"]["colmap.zip"]).content)) as archive:
            assert sorted(archive.namelist()) == ["cameras.txt", "images.txt", "points3D.txt"]
        assert client.get(f"/api/jobs/{job['id']}/files/..%2F..%2Fetc%2Fpasswd").status_code == 404
        assert client.get("/api/jobs/nope").status_code == 404
        paths = client.get("/openapi.json").json()["paths"]
        assert {"/api/jobs", "/api/jobs/{job_id}", "/api/jobs/{job_id}/files/{name}"} <= set(paths)
        assert client.get("/docs").status_code == 200 and "Stitch" in client.get("/").text
    assert not root.exists()  # every job's files are deleted at shutdown


def test_a_panorama_job_offers_its_files_but_no_colmap_model(small_pair):
    from pis3r.web.work import DOWNLOADS

    with TestClient(create_app(LIMITS)) as client:
        files = [(f"{i}.png", png(a), "image/png") for i, a in enumerate(small_pair)]
        response = post(client, files, backend="classical", projection="cylindrical")
        assert response.status_code == 202, response.text
        job = wait(client, response.json()["id"])
        assert job["status"] == "done", job
        result = job["result"]
        assert result["projection"] == "cylindrical"
        assert set(result["files"]) == set(DOWNLOADS) - {"colmap.zip"}
        assert client.get(result["files"]["camera.json"]).json()["model"] == "cylindrical"
        assert client.get(result["files"]["overlay.png"]).content.startswith(b"\x89PNG")
        assert client.get(f"/api/jobs/{job['id']}/files/colmap.zip").status_code == 404


def test_queue_is_bounded_and_expired_jobs_are_deleted(tmp_path):
    release = threading.Event()
    jobs = JobQueue(lambda job: release.wait(10) and {}, workers=1, max_queued=1, ttl_s=0.0)
    try:
        made = []
        for _ in range(2):
            job_id, directory = jobs.new_directory()
            made.append(Job(job_id, directory, [], [], {"ref": 0}))
            jobs.submit(made[-1])
            time.sleep(0.2)  # the first job is picked up and runs; the second waits
        job_id, directory = jobs.new_directory()
        with pytest.raises(ServerBusyError):
            jobs.submit(Job(job_id, directory, [], [], {"ref": 0}))
        assert not directory.exists() and jobs.position(made[1]) == 0
        release.set()
        deadline = time.monotonic() + 10
        while any(job.directory.exists() for job in made) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert all(job.status == "done" and not job.directory.exists() for job in made)
        assert jobs.get(made[0].id) is None
    finally:
        release.set()
        jobs.close()
    assert not jobs.root.exists()
