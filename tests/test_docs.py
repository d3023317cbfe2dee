"""The documentation: a short README whose example runs, docs that never link outside the
repository. (The docs build itself -- warnings as errors, every tutorial executed -- is a step
of ``make test``: ``make docs``.)"""

import pathlib
import re
import subprocess
import sys

ROOT = pathlib.Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
README_MAX_BYTES = 8 * 1024
DOC_SOURCES = [README, *sorted((ROOT / "docs").rglob("*.md"))]
DOC_SOURCES = [p for p in DOC_SOURCES if "_build" not in p.parts]

# a Markdown link or image target, an autolink, or a bare URL
LINK = re.compile(r"\]\(([^)\s]+)[^)]*\)")
URL = re.compile(r"\b(?:https?|ftp)://|\bwww\.", re.IGNORECASE)
# a relative path that climbs directories: it must stay inside the repository
PARENT_PATH = re.compile(r"(?:\.\./)+[\w.-]+(?:/[\w.-]+)*")


def _code_blocks(text: str, lang: str) -> list[str]:
    return re.findall(rf"^```{lang}\n(.*?)^```$", text, flags=re.MULTILINE | re.DOTALL)


def test_readme_is_short():
    assert README.stat().st_size <= README_MAX_BYTES, f"README.md is {README.stat().st_size} bytes"


def test_no_link_leaves_the_repository():
    bad = []
    for page in DOC_SOURCES:
        text = page.read_text(encoding="utf-8")
        for n, line in enumerate(text.splitlines(), 1):
            outside = [m for m in PARENT_PATH.findall(line) if not (page.parent / m).resolve().is_relative_to(ROOT)]
            if URL.search(line) or outside:
                bad.append(f"{page.relative_to(ROOT)}:{n}: {line.strip()}")
        for target in LINK.findall(text):
            if target.startswith("#"):
                continue
            path = (page.parent / target.split("#")[0]).resolve()
            if not path.is_relative_to(ROOT) or not path.exists():
                bad.append(f"{page.relative_to(ROOT)}: link to {target} (missing or outside the repository)")
    assert not bad, "\n".join(bad)


def test_readme_example_runs(tmp_path):
    blocks = _code_blocks(README.read_text(encoding="utf-8"), "python")
    assert len(blocks) == 1, "the README has one Python example"
    script = tmp_path / "readme_example.py"
    script.write_text(blocks[0])
    done = subprocess.run(
        [sys.executable, str(script)],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        env={"PATH": "/usr/bin:/bin", "JAX_PLATFORMS": "cpu", "HOME": str(tmp_path)},
    )
    assert done.returncode == 0, done.stderr[-3000:]
    # the two radii the example prints: eq (64)'s 0.768 (the paper's §6.1) and the exact map's
    # 8.79 m of the position slice (tests/test_certify*.py check both against their oracles)
    paper, exact = (float(x) for x in done.stdout.split())
    assert abs(paper - 0.7682) < 1e-4 and abs(exact - 8.7896) < 1e-4


def test_the_benchmark_tables_are_their_records(tmp_path, monkeypatch):
    """Every generated table of the pages (docs/benchmarks.md, the certify page) is what
    benchmarks.page renders from the benchmark's record (a number edited by hand, or a record not
    rendered, fails), and every table the renderer knows is on a page."""
    import json

    from benchmarks import page

    texts = [p.read_text() for p in page.PAGES]
    names = [m.group("name") for text in texts for m in page.BLOCK.finditer(text)]
    assert sorted(names) == sorted(page.TABLES), "a table on a page without a renderer, or the reverse"
    for text in texts:
        assert page.regenerate(text) == text, "run python -m benchmarks.page"
        for m in page.BLOCK.finditer(text):
            assert m.group("body").count("\n|") >= 2, f"{m.group('name')}: no table rendered"
    # the check can fail: a record changed after the page was rendered
    (tmp_path / "records").mkdir()
    for f in page.RECORDS.glob("*.json"):
        r = json.loads(f.read_text())
        r["date"] = "1999-01-01"
        (tmp_path / "records" / f.name).write_text(json.dumps(r))
    monkeypatch.setattr(page, "RECORDS", tmp_path / "records")
    assert page.regenerate(texts[0]) != texts[0]


def test_the_benchmarks_page_holds_current_numbers_only():
    """docs/benchmarks.md stays within the 20 KB that issue 55 set for current numbers (its
    history is in git; it was a 114 KB lab log)."""
    size = (ROOT / "docs" / "benchmarks.md").stat().st_size
    assert size <= 20_000, f"docs/benchmarks.md is {size} bytes: move superseded numbers out (history is in git)"
