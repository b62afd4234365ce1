"""Every Python code block of the documentation (`docs/**/*.md` and `README.md`) runs.

- The blocks of one page run in order, in one namespace (a page builds on its earlier
  blocks), in a fresh working directory (a page may write files), one test per page.
- A block that cannot run here (two processes, a cluster, a GPU, a long run) is marked in
  the Markdown by an HTML comment on the line before its fence, `<!-- skip: REASON -->`
  (hidden in the built site); it gets its own test, reported skipped with that reason.
- A page whose blocks take long to compile is `extended` (`EXTENDED_PAGES`).
- The two-process script of `docs/cluster.md` runs as two processes
  (`test_cluster_script_in_two_processes`).

A failing block's traceback names the page and the line of the Markdown file.
"""

import os
import re
import socket
import subprocess
import sys
from pathlib import Path

import jax
import pytest

ROOT = Path(__file__).resolve().parent.parent
PAGES = sorted([ROOT / "README.md", *(ROOT / "docs").rglob("*.md")])
FENCE = re.compile(r"^(?P<indent>\s*)```(?:python|py)\s*$")
SKIP = re.compile(r"^\s*<!--\s*skip:\s*(?P<reason>.+?)\s*-->\s*$")


def code_blocks(path: Path) -> list[tuple[int, str, str | None]]:
    """`(line, source, skip reason or None)` of each Python block of a Markdown page, in
    order; `line` is the 1-based line of the block's first line of code."""
    lines = path.read_text().splitlines()
    blocks, k = [], 0
    while k < len(lines):
        fence = FENCE.match(lines[k])
        if fence is None:
            k += 1
            continue
        before = next((line for line in reversed(lines[:k]) if line.strip()), "")
        skip = SKIP.match(before)
        indent, start = len(fence["indent"]), k + 1
        k = start
        while not re.match(r"^\s*```\s*$", lines[k]):
            k += 1
        source = "\n".join(line[indent:] for line in lines[start:k])
        blocks.append((start + 1, source, skip["reason"] if skip else None))
        k += 1
    return blocks


def _name(path: Path) -> str:
    return path.relative_to(ROOT).as_posix()


BLOCKS = {_name(p): code_blocks(p) for p in PAGES}
# The pages whose blocks compile fits, coupled bodies or SE(3) programs (seconds on one
# worker of a 2-core machine); the quick-start pages stay in the default suite.
EXTENDED_PAGES = (
    "docs/identification.md",  # 70 s
    "docs/rigid-bodies.md",  # 67 s
    "docs/optimal-control.md",  # 58 s
    "docs/forcing.md",  # 55 s
    "docs/gradients.md",  # 40 s
    "docs/se3.md",  # 24 s
    "docs/potentials.md",  # 22 s
    "docs/preprocessed_dmv.md",  # 15 s
)
RUN = [
    pytest.param(name, marks=pytest.mark.extended) if name in EXTENDED_PAGES else name
    for name, blocks in BLOCKS.items()
    if any(s is None for _, _, s in blocks)
]
SKIPPED = [
    pytest.param(name, line, reason, id=f"{name}:{line}")
    for name, blocks in BLOCKS.items()
    for line, _, reason in blocks
    if reason is not None
]


@pytest.fixture
def restored_jax_config():
    """A page may set JAX options (a compilation cache, x64): they are put back after it."""
    before = dict(jax.config.values)
    yield
    for key, value in before.items():
        if jax.config.values.get(key) != value:
            jax.config.update(key, value)


@pytest.mark.parametrize("page", RUN)
def test_page_examples_run(page, tmp_path, monkeypatch, restored_jax_config):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("MPLBACKEND", "Agg")
    namespace = {"__name__": "__main__"}
    for line, source, skip in BLOCKS[page]:
        if skip is None:
            # Padded so that a traceback's line number is the Markdown file's.
            code = compile("\n" * (line - 1) + source, str(ROOT / page), "exec")
            exec(code, namespace)


@pytest.mark.parametrize(("page", "line", "reason"), SKIPPED)
def test_marked_block(page, line, reason):
    pytest.skip(f"{page}:{line}: {reason}")


def test_collector_reads_blocks_and_marks(tmp_path):
    """Blocks are found in order (indented ones too), with their Markdown line and the
    reason of a `skip` comment; other languages are left out."""
    page = tmp_path / "page.md"
    page.write_text(
        "# Title\n\n```python\nx = 1\n```\n\n<!-- skip: needs two processes -->\n"
        "```python\nimport sys\n```\n\n```bash\nls\n```\n\n- item\n\n"
        "    ```python\n    y = x + 1\n    ```\n"
    )
    assert code_blocks(page) == [
        (4, "x = 1", None),
        (9, "import sys", "needs two processes"),
        (19, "y = x + 1", None),
    ]
    assert "README.md" in RUN and "docs/index.md" in RUN
    assert {p.values[0] for p in SKIPPED} == {"docs/cluster.md"}  # its script runs below


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.parametrize(
    "with_fit",
    [
        pytest.param(False, marks=pytest.mark.extended),  # 72 s
        pytest.param(True, marks=pytest.mark.slow),
    ],
)
def test_cluster_script_in_two_processes(tmp_path, with_fit):
    """The script of "Two processes on one machine" (with `-m slow`, and its fit), as the
    page says to start it (twice, process ids 0 and 1), on this machine's CPU, on a free
    port instead of the page's."""
    (_, script, reason), (_, fit, fit_reason), *_ = BLOCKS["docs/cluster.md"]
    assert reason is not None and fit_reason is not None
    assert script.count("127.0.0.1:12355") == 1 and "fit_system" in fit
    source = script.replace("127.0.0.1:12355", f"127.0.0.1:{_free_port()}")
    shapes = "d_inertia.shape, all_m.shape, mine_m.shape" + (", params.shape" if with_fit else "")
    (tmp_path / "run.py").write_text(
        f"{source}\n{fit if with_fit else ''}\nprint('done', {shapes}, flush=True)\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}  # one device a process
    env.update(JAX_PLATFORMS="cpu", PYTHONPATH=str(ROOT))
    processes = [
        subprocess.Popen(
            [sys.executable, "run.py", str(p)],
            cwd=tmp_path,
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        for p in range(2)
    ]
    try:
        logs = [p.communicate(timeout=600)[0] for p in processes]
    finally:
        for p in processes:
            p.kill()
    for log in logs:
        expected = "done (64, 3) (64, 11, 3) (32, 11, 3)" + (" (64, 3)" if with_fit else "")
        assert expected in log, log
