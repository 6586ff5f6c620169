"""Start-up cost (issue 12): the classical CPU path and ``--help`` never import torch.

Timing is not asserted (benchmarks/speed.py measures it); what is asserted is the cause of
the slow start: torch is a 2 s import, needed only by VGGT, the refiner and CUDA.
"""

import subprocess
import sys

import pytest

STITCH_WITHOUT_TORCH = r"""
import sys
import numpy as np
from skimage import data
import pis3r

photo = data.astronaut()[::2, ::2]
result = pis3r.stitch([photo[20:180, 0:190].copy(), photo[30:190, 60:250].copy()], backend="classical")
assert result.image.shape[1] > 190, result.image.shape
print("torch" in sys.modules, "scipy" in sys.modules, "scipy.optimize" in sys.modules, "scipy.spatial" in sys.modules)
"""


AUTO_BACKEND_WITHOUT_WEIGHTS = r"""
import sys
from pis3r.reconstruct.base import resolve_backend_name
from pis3r.reconstruct.options import ReconstructOptions

print(resolve_backend_name("auto", ReconstructOptions()), "huggingface_hub.file_download" in sys.modules)
"""

WARM_UP_IN_BACKGROUND = r"""
import sys
from pis3r import gl
from pis3r.warmup import CLASSICAL_MODULES, warm_up_in_background

before = [name in sys.modules for name in CLASSICAL_MODULES] + ["context" in gl._state]
warm_up_in_background().join()
print(any(before), all(name in sys.modules for name in CLASSICAL_MODULES), gl._state["context"] is not None,
      warm_up_in_background())
"""


def _python(*args: str) -> str:
    proc = subprocess.run([sys.executable, *args], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return proc.stdout


def test_a_classical_stitch_on_the_cpu_never_imports_torch_nor_scipy_optimize():
    """scipy's sparse solvers fill depth; its general optimiser (0.2 s to import) is not
    needed: the pose and rotation fits are pis3r.reconstruct.robust_lsq; nor is its k-d tree
    (0.12 s) where SIFT matches the pair: only ASIFT's match refinement uses it."""
    assert _python("-c", STITCH_WITHOUT_TORCH).split() == ["False", "True", "False", "False"]


def test_the_solvers_and_the_gl_context_a_stitch_needs_are_made_on_a_thread_once():
    """The classical path imports scipy's solvers and creates the OpenGL context on a thread
    while OpenCV finds features: once it ends both are there, and a second call has nothing
    left to start."""
    assert _python("-c", WARM_UP_IN_BACKGROUND).split() == ["False", "True", "True", "None"]


def test_looking_for_vggt_weights_in_an_empty_cache_imports_no_download_machinery(tmp_path, monkeypatch):
    """``--backend auto`` (the default) looks for VGGT weights first: on a machine that never
    fetched them the answer must not cost huggingface_hub's download stack (0.1 s a run)."""
    monkeypatch.setenv("HF_HUB_CACHE", str(tmp_path))
    monkeypatch.delenv("PIS3R_VGGT_WEIGHTS", raising=False)
    assert _python("-c", AUTO_BACKEND_WITHOUT_WEIGHTS).split() == ["classical", "False"]


@pytest.mark.parametrize("args", [["--help"], ["stitch", "--help"], ["batch", "--help"]])
def test_help_imports_neither_torch_nor_scipy(args):
    # What the installed ``pis3r`` script runs (pyproject: pis3r.cli:run, which calls main).
    code = ("import sys\nfrom pis3r.cli import main\n"
            "try:\n    main(sys.argv[1:], prog_name='pis3r')\nexcept SystemExit:\n    pass\n"
            "print('torch' in sys.modules, 'scipy' in sys.modules, file=sys.stderr)")
    proc = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, timeout=120)
    assert "Usage:" in proc.stdout
    assert proc.stderr.split()[-2:] == ["False", "False"], proc.stderr[-2000:]


def test_the_program_imports_the_synth_renderer_only_when_synth_runs():
    """Every command imports the modules that list the subcommands; the synth scenes and
    renderer (24 ms) wait for ``pis3r synth`` itself."""
    code = "import sys\nimport pis3r.cli\nprint('pis3r.synth.dataset' in sys.modules)"
    assert _python("-c", code).split() == ["False"]


REFAULTS_OF_A_FREED_ARRAY = r"""
import resource, sys
import cv2
import numpy as np
from pis3r.cli import reuse_freed_memory

applied = reuse_freed_memory() if sys.argv[1] == "reuse" else None
image = np.ones((1000, 1000), np.float32)
# An image OpenCV allocates (with malloc), 4 MB, touched, then freed.
cv2.add(image, 1.0)
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
cv2.add(image, 1.0)
print(applied, resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


def _faults_with_and_without_the_command_s_heap_settings(code: str) -> tuple[int, int]:
    """The page faults ``code`` prints after ``reuse_freed_memory`` and without it (skips the
    test where the C library has no ``mallopt``)."""
    applied, faults = _python("-c", code, "reuse").split()
    if applied != "True":
        pytest.skip("the C library has no mallopt (not glibc)")
    _, default_faults = _python("-c", code, "default").split()
    return int(faults), int(default_faults)


def test_the_command_keeps_freed_arrays_for_the_next_stage_instead_of_faulting_them_in_again():
    """``pis3r`` raises glibc's mmap threshold (``reuse_freed_memory``): an image that OpenCV
    allocated, freed and allocates again costs no new page faults (by default glibc hands
    the block back and takes fresh pages: one fault per 4 KB page)."""
    faults, default_faults = _faults_with_and_without_the_command_s_heap_settings(REFAULTS_OF_A_FREED_ARRAY)
    assert default_faults > 500 and faults < 50


REFAULTS_OF_AN_ARRAY_ANOTHER_THREAD_FREED = r"""
import resource, sys, threading
import cv2
import numpy as np
from pis3r.cli import reuse_freed_memory

applied = reuse_freed_memory() if sys.argv[1] == "reuse" else None
image, small = np.ones((1000, 1000), np.float32), np.ones((8, 8), np.float32)
both_started = threading.Barrier(2)


def worker(turn: threading.Event, done: threading.Event) -> None:
    # Two threads alive together, as a stage's pool: by default each allocates from its own arena.
    cv2.add(small, 1.0)
    both_started.wait()
    turn.wait()
    # A 4 MB image OpenCV allocates (malloc), touches and frees.
    cv2.add(image, 1.0)
    done.set()


# The main thread allocates from the heap first, as the command does before its stages start.
cv2.add(image, 1.0)
turns, dones = [threading.Event(), threading.Event()], [threading.Event(), threading.Event()]
threads = [threading.Thread(target=worker, args=pair) for pair in zip(turns, dones)]
for thread in threads:
    thread.start()
turns[0].set()
dones[0].wait()
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
turns[1].set()
dones[1].wait()
print(applied, resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
for thread in threads:
    thread.join()
"""


def test_the_command_serves_every_thread_from_one_heap_so_a_worker_reuses_what_another_freed():
    """``pis3r`` keeps one malloc arena (``ARENAS``): a block a worker thread freed is reused by
    the next worker instead of each faulting in fresh pages in an arena of its own."""
    faults, default_faults = _faults_with_and_without_the_command_s_heap_settings(
        REFAULTS_OF_AN_ARRAY_ANOTHER_THREAD_FREED)
    assert default_faults > 500 and faults < 100


PROGRAM_WITH_AN_EXIT_HOOK = r"""
import atexit, sys
from pis3r.cli import run

atexit.register(lambda: print("teardown ran", file=sys.stderr))
sys.argv = ["pis3r", *sys.argv[1:]]
run()
"""


@pytest.mark.parametrize("args, teardown", [
    (["stitch", "--help"], False),
    (["stitch", "missing.jpg", "other.jpg", "-o", "out"], False),
    (["synth", "--help"], False),
    (["serve", "--help"], True),
    (["batch", "--help"], True),
    (["eval", "--help"], True),
    (["train-refiner", "--help"], True),
])
def test_the_program_ends_at_once_after_a_one_off_command_with_its_output_and_exit_code(args, teardown, tmp_path):
    """``pis3r`` (:func:`pis3r.cli.run`) skips Python's teardown after a command that starts no
    other process, yet what it printed arrives and its exit code is kept; after commands that
    start a server, worker processes or a process pool the teardown (their shutdown hooks) runs."""
    proc = subprocess.run([sys.executable, "-c", PROGRAM_WITH_AN_EXIT_HOOK, *args], capture_output=True,
                          text=True, timeout=120, cwd=tmp_path)
    if "--help" in args:
        assert proc.returncode == 0 and "Usage:" in proc.stdout, proc.stderr[-2000:]
    else:
        errors = [line for line in proc.stderr.splitlines() if line.startswith("pis3r: error")]
        assert proc.returncode != 0 and len(errors) == 1 and "missing.jpg" in errors[0], proc.stderr[-2000:]
    assert ("teardown ran" in proc.stderr) == teardown


@pytest.mark.parametrize("command, applied", [("stitch", True), ("batch", True), ("serve", False)])
def test_one_off_commands_keep_freed_memory_and_the_web_server_hands_it_back(command, applied, monkeypatch):
    from click.testing import CliRunner

    import pis3r.cli

    calls = []
    monkeypatch.setattr(pis3r.cli, "reuse_freed_memory", lambda: calls.append(command))
    # The group's own code runs before the subcommand parses its options (here: --help).
    result = CliRunner().invoke(pis3r.cli.main, [command, "--help"])
    assert result.exit_code == 0 and calls == ([command] if applied else [])


def test_off_linux_the_heap_is_left_as_it_is(monkeypatch):
    import pis3r.cli

    monkeypatch.setattr(pis3r.cli.sys, "platform", "win32")
    assert pis3r.cli.reuse_freed_memory() is False


BLAS_THREADS_DURING_A_STITCH = r"""
import numpy as np
from skimage import data
from threadpoolctl import threadpool_info, threadpool_limits
import pis3r
import pis3r.api

def blas_threads():
    return sorted({lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"})

seen = {}
choose_model = pis3r.api.choose_model
def recording(*args, **kwargs):
    seen["during"] = blas_threads()
    return choose_model(*args, **kwargs)
pis3r.api.choose_model = recording

photo = data.astronaut()[::2, ::2]
pair = [photo[20:180, 0:190].copy(), photo[30:190, 60:250].copy()]
with threadpool_limits(2, user_api="blas"):
    pis3r.stitch(pair, backend="classical")
    print(seen["during"], blas_threads())
"""


def test_blas_runs_one_thread_during_a_classical_stitch_and_is_restored_after():
    """OpenBLAS's idle helper thread spins and takes a core from pis3r's own threads: one
    thread while a classical stitch runs, whatever the caller had again once it returns."""
    assert _python("-c", BLAS_THREADS_DURING_A_STITCH).strip() == "[1] [2]"
