"""A bounded job queue for the web page: worker threads, one temp folder per job, expiry.

Jobs wait in a FIFO queue of at most ``max_queued`` entries and run on ``workers``
threads (stitching is memory-hungry: one at a time by default). Every job owns a
folder under one root temp folder; a finished job's folder is deleted ``ttl_s``
seconds after it finished, and the whole root when the queue is closed.
"""

from __future__ import annotations

import queue
import shutil
import tempfile
import threading
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Callable

from pis3r.errors import Pis3rError

if TYPE_CHECKING:
    from pis3r.options import StitchOptions

# How often idle workers wake up to delete expired jobs.
PURGE_INTERVAL_S = 30.0


class ServerBusyError(Pis3rError):
    """The job queue is full; the client should try again later."""


@dataclass
class Job:
    """One stitch request: its inputs (saved in ``directory``), options and state.

    ``status``: ``queued`` -> ``running`` -> ``done`` | ``failed``; ``error`` is a
    one-line message when failed; ``result`` what the page shows when done.
    """

    id: str
    directory: Path
    inputs: list[Path]
    names: list[str]
    options: StitchOptions
    status: str = "queued"
    error: str = ""
    result: dict = field(default_factory=dict)
    created: float = field(default_factory=time.monotonic)
    started: float | None = None
    finished: float | None = None


class JobQueue:
    """Runs ``run(job) -> result dict`` for submitted jobs on worker threads."""

    def __init__(self, run: Callable[[Job], dict], workers: int = 1, max_queued: int = 4, ttl_s: float = 3600.0):
        self.root = Path(tempfile.mkdtemp(prefix="pis3r-web-"))
        self._run = run
        self._max_queued = max_queued
        self._ttl_s = ttl_s
        self._jobs: dict[str, Job] = {}
        self._waiting: queue.Queue[Job | None] = queue.Queue()
        self._lock = threading.Lock()
        self._threads = [threading.Thread(target=self._work, name=f"pis3r-job-{i}", daemon=True)
                         for i in range(workers)]
        for thread in self._threads:
            thread.start()

    def new_directory(self) -> tuple[str, Path]:
        """A fresh job id and its empty folder."""
        job_id = uuid.uuid4().hex
        directory = self.root / job_id
        directory.mkdir()
        return job_id, directory

    def submit(self, job: Job) -> None:
        with self._lock:
            if sum(j.status == "queued" for j in self._jobs.values()) >= self._max_queued:
                shutil.rmtree(job.directory, ignore_errors=True)
                raise ServerBusyError(f"{self._max_queued} jobs are already waiting; try again in a minute")
            self._jobs[job.id] = job
        self._waiting.put(job)

    def get(self, job_id: str) -> Job | None:
        with self._lock:
            return self._jobs.get(job_id)

    def position(self, job: Job) -> int:
        """How many queued jobs were submitted before ``job`` (0 = next)."""
        with self._lock:
            return sum(j.status == "queued" and j.created < job.created for j in self._jobs.values())

    def purge_expired(self) -> None:
        """Forget finished jobs older than the TTL and delete their folders."""
        now = time.monotonic()
        with self._lock:
            expired = [j for j in self._jobs.values() if j.finished is not None and now - j.finished > self._ttl_s]
            for job in expired:
                del self._jobs[job.id]
        for job in expired:
            shutil.rmtree(job.directory, ignore_errors=True)

    def close(self) -> None:
        """Stop the workers (a running job finishes first) and delete every job folder."""
        for _ in self._threads:
            self._waiting.put(None)
        for thread in self._threads:
            thread.join(timeout=60)
        shutil.rmtree(self.root, ignore_errors=True)

    def _work(self) -> None:
        while True:
            try:
                job = self._waiting.get(timeout=PURGE_INTERVAL_S)
            except queue.Empty:
                self.purge_expired()
                continue
            if job is None:
                return
            job.started, job.status = time.monotonic(), "running"
            try:
                job.result = self._run(job)
                job.status = "done"
            except Pis3rError as exc:
                job.error, job.status = str(exc), "failed"
            except MemoryError:
                job.error, job.status = "out of memory (try smaller images)", "failed"
            except Exception as exc:  # one broken job must not kill the worker
                job.error, job.status = f"internal error: {exc.__class__.__name__}: {exc}", "failed"
            job.finished = time.monotonic()
            self.purge_expired()
