"""The HTTP API and the page: ``create_app()`` returns a FastAPI app (OpenAPI at ``/docs``).

``GET /api/options`` lists the form's options with their choices and defaults (from
:class:`pis3r.StitchOptions`), ``POST /api/jobs`` (multipart ``files`` + ``ref``,
``backend``, ``matcher``, ``projection``, ``blend``) queues a stitch,
``GET /api/jobs/{id}`` reports its progress and result, ``GET /api/jobs/{id}/files/{name}``
serves its outputs. Errors are JSON ``{"detail": "one line"}`` with 400 (bad input),
413 (over a limit), 404 (unknown job or file) or 503 (queue full).
"""

from __future__ import annotations

import time
from contextlib import asynccontextmanager
from dataclasses import dataclass
from importlib import resources

from fastapi import FastAPI, File, Form, HTTPException, Request, UploadFile
from fastapi.responses import FileResponse, HTMLResponse, JSONResponse

from pis3r.errors import InputError, Pis3rError
from pis3r.options import StitchOptions
from pis3r.web.jobs import Job, JobQueue, ServerBusyError
from pis3r.web.uploads import UploadTooLargeError, check_image, read_limited, safe_name
from pis3r.web.work import DOWNLOADS, run_stitch_job


@dataclass(frozen=True)
class WebLimits:
    """What one server accepts: per-file bytes and pixels, files per job, waiting jobs,
    concurrently running jobs, and how long a finished job's files are kept."""

    max_file_bytes: int = 25 * 2**20
    max_pixels: int = 16_000_000
    max_files: int = 8
    max_queued_jobs: int = 4
    workers: int = 1
    job_ttl_s: float = 3600.0


# The StitchOptions fields the page offers besides the reference.
FORM_OPTIONS = ("backend", "matcher", "projection", "blend")


def _form_option(name: str):
    """A form field for StitchOptions field ``name``: its default, choices and help."""
    spec = StitchOptions.field(name)
    return Form(spec.default, description=spec.metadata["help"],
                json_schema_extra={"enum": list(spec.metadata["choices"])})


def _status_code(exc: Pis3rError) -> int:
    if isinstance(exc, UploadTooLargeError):
        return 413
    if isinstance(exc, ServerBusyError):
        return 503
    return 400 if isinstance(exc, InputError) else 500


def job_status(job: Job, jobs: JobQueue) -> dict:
    """The JSON the page polls: state, queue position, seconds running, result and file URLs."""
    now = time.monotonic()
    status = {
        "id": job.id,
        "status": job.status,
        "error": job.error,
        "inputs": job.names,
        "ref": job.options.ref,
        "position": jobs.position(job) if job.status == "queued" else 0,
        "elapsed_s": round(((job.finished or now) - job.started), 1) if job.started else 0.0,
    }
    if job.status == "done":
        files = {name: f"/api/jobs/{job.id}/files/{name}" for name in job.result.get("downloads", DOWNLOADS)}
        status["result"] = {**job.result, "files": files}
    return status


def create_app(limits: WebLimits = WebLimits()) -> FastAPI:
    """The pis3r web app with its own job queue (started now, emptied and deleted at shutdown)."""
    jobs = JobQueue(run_stitch_job, workers=limits.workers, max_queued=limits.max_queued_jobs,
                    ttl_s=limits.job_ttl_s)

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        yield
        jobs.close()

    app = FastAPI(title="pis3r", summary="Stitch photos taken from different positions into one perspective "
                  "image of a reference camera.", lifespan=lifespan)
    app.state.jobs = jobs
    app.state.limits = limits

    @app.exception_handler(Pis3rError)
    async def pis3r_error(request: Request, exc: Pis3rError):
        return JSONResponse({"detail": str(exc)}, status_code=_status_code(exc))

    @app.middleware("http")
    async def refuse_oversized_bodies(request: Request, call_next):
        # Refuse before the body is spooled to disk; per-file limits are checked again below.
        declared = request.headers.get("content-length", "")
        if declared.isdigit() and int(declared) > limits.max_files * limits.max_file_bytes + 2**20:
            return JSONResponse({"detail": "upload is larger than the server accepts"}, status_code=413)
        return await call_next(request)

    @app.get("/", response_class=HTMLResponse, include_in_schema=False)
    def page() -> str:
        return resources.files("pis3r.web").joinpath("static/index.html").read_text()

    @app.get("/api/options", summary="The options the form offers, with their choices and defaults")
    def options() -> dict:
        return {name: {"default": StitchOptions.default(name), "choices": list(StitchOptions.choices(name)),
                       "help": StitchOptions.field(name).metadata["help"]} for name in FORM_OPTIONS}

    @app.post("/api/jobs", status_code=202, summary="Queue a stitch of 2 or more photos")
    def submit(
        files: list[UploadFile] = File(description="Two or more photos of one scene"),
        ref: int = Form(0, description="Index of the reference photo (its camera is the output camera)"),
        backend: str = _form_option("backend"),
        matcher: str = _form_option("matcher"),
        projection: str = _form_option("projection"),
        blend: str = _form_option("blend"),
    ) -> dict:
        if len(files) < 2:
            raise InputError(f"need at least 2 photos to stitch, got {len(files)}")
        if len(files) > limits.max_files:
            raise UploadTooLargeError(f"at most {limits.max_files} photos per job, got {len(files)}")
        if not 0 <= ref < len(files):
            raise InputError(f"reference must be a photo index 0..{len(files) - 1}, got {ref}")
        options = StitchOptions(ref=ref, backend=backend, matcher=matcher, projection=projection, blend=blend)
        names = [safe_name(upload.filename, index) for index, upload in enumerate(files)]
        contents = []
        for name, upload in zip(names, files):
            data = read_limited(upload.file, name, limits.max_file_bytes)
            check_image(data, name, limits.max_pixels)
            contents.append(data)
        job_id, directory = jobs.new_directory()
        inputs = []
        for index, (name, data) in enumerate(zip(names, contents)):
            inputs.append(directory / f"{index:02d}_{name}")
            inputs[-1].write_bytes(data)
        job = Job(job_id, directory, inputs, names, options)
        jobs.submit(job)
        return job_status(job, jobs)

    def find(job_id: str) -> Job:
        job = jobs.get(job_id)
        if job is None:
            raise HTTPException(404, "no such job (finished jobs are deleted after a while)")
        return job

    @app.get("/api/jobs/{job_id}", summary="Progress and result of a job")
    def status(job_id: str) -> dict:
        return job_status(find(job_id), jobs)

    @app.get("/api/jobs/{job_id}/files/{name}", summary="Download one output of a finished job")
    def download(job_id: str, name: str) -> FileResponse:
        job = find(job_id)
        if job.status != "done" or name not in job.result.get("downloads", DOWNLOADS):
            raise HTTPException(404, f"no file {name!r} for this job")
        return FileResponse(job.directory / "out" / name, filename=name)

    return app
