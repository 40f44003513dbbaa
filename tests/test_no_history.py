"""The product describes what it is, not how it got there.

README.md, docs/ (except the changelog), workflow/, config/, tests/ and benchmarks/ must not
narrate the project's development: no numbered work periods (the word spelt in ``WORD``;
pytest's fixture scope and hook names excepted) and no commit hashes. History lives in git and in ``docs/changelog.md``.

Each hit is reported as ``file:line: text``.
"""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: the folders and files scanned (relative to the repository root)
SCANNED = ("README.md", "docs", "workflow", "config", "tests", "benchmarks")
#: text files scanned, by suffix
SUFFIXES = {".py", ".smk", ".md", ".yaml", ".yml", ".rst", ".txt", ".json", ".jsonl", ".cfg",
            ".toml", ".sh"}
#: the one place history may live
EXEMPT = {"docs/changelog.md"}
#: machine-readable result records carry the commit they were measured at by design
HASH_EXEMPT_DIRS = ("benchmarks/results/",)

#: the word looked for (spelt in two pieces so that this file does not contain it)
WORD = "ses" "sion"
# pytest's own uses of the word: the fixture scope, the hooks and the object they receive
_ALLOWED = re.compile(
    rf"""scope\s*=\s*["']{WORD}["']"""              # @pytest.fixture(scope=…)
    rf"|\bpytest_{WORD}\w*\b(\s*\(\s*{WORD}\b)?"    # the start and finish hooks
    rf"|\b(request|item|node|config)\.{WORD}\b"      # the fixture request's attribute
    rf"|\b{WORD}\.(config|items|testscollected|testsfailed|shouldstop|shouldfail|exitstatus)\b"
    rf"|\brequests\.{WORD.capitalize()}\b"           # the requests library's class
    rf"|\bstart_new_{WORD}\b"                         # subprocess.Popen's argument
    rf"|\b{WORD}Id\b",                                # the DevTools protocol's field name
)
_WORD_RE = re.compile(WORD, re.IGNORECASE)

# a hex token of 7–40 digits with at least one letter a–f and one decimal digit, not part of a
# longer word, a hex colour (#1f77b4), a 0x literal or a digest (sha256:…, 64 digits)
_HEX = re.compile(r"(?<![#\w])(?<!0x)(?=[0-9a-f]*[a-f])(?=[0-9a-f]*[0-9])[0-9a-f]{7,40}(?![\w-])")
# … counted as a commit hash when one of these words stands just before it
_HASH_CONTEXT = re.compile(
    r"\b(commit\w*|at|of|on|in|from|archive|rev\w*|git|hash|sha|head|before|after|since|until|"
    r"code|checkout|tree)\b[\s\"':=(`]*$",
    re.IGNORECASE,
)


def _files():
    """The scanned files: those git tracks or would track (build outputs such as the generated
    reference pages are git-ignored and left out); every file when git is not available."""
    try:
        out = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard",
                              "--", *SCANNED], cwd=ROOT, capture_output=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        out = None
    if out is not None:
        for rel in sorted(set(out.decode().split("\0")) - {""}):
            p = ROOT / rel
            if p.is_file() and p.suffix in SUFFIXES:
                yield p
        return
    for name in SCANNED:
        path = ROOT / name
        if path.is_file():
            yield path
        elif path.is_dir():
            for p in sorted(path.rglob("*")):
                if p.is_file() and p.suffix in SUFFIXES and "__pycache__" not in p.parts:
                    yield p


def word_hits(line: str) -> bool:
    """True when ``line`` uses :data:`WORD` outside pytest's fixture scope and hooks."""
    return bool(_WORD_RE.search(_ALLOWED.sub("", line)))


def hash_hits(line: str) -> list[str]:
    """The commit-hash-like tokens of ``line`` that follow a word such as commit / at / of."""
    return [m.group(0) for m in _HEX.finditer(line)
            if _HASH_CONTEXT.search(line[max(0, m.start() - 24):m.start()])]


def scan(root: Path = ROOT) -> list[str]:
    """Every hit under ``root`` as ``relative/path:line: kind: text``."""
    hits = []
    for path in _files():
        rel = path.relative_to(root).as_posix()
        if rel in EXEMPT:
            continue
        try:
            text = path.read_text(encoding="utf-8")
        except (UnicodeDecodeError, OSError):
            continue
        check_hashes = not rel.startswith(HASH_EXEMPT_DIRS)
        for no, line in enumerate(text.splitlines(), 1):
            if word_hits(line):
                hits.append(f"{rel}:{no}: {WORD}: {line.strip()[:120]}")
            if check_hashes:
                for token in hash_hits(line):
                    hits.append(f"{rel}:{no}: commit hash {token}: {line.strip()[:120]}")
    return hits


def test_the_allow_lists_are_precise():
    assert not word_hits(f'@pytest.fixture(scope="{WORD}")')
    assert not word_hits(f"def pytest_{WORD}start({WORD}):")
    assert not word_hits(f"    cfg = request.{WORD}.config")
    assert word_hits(f"measured in {WORD} 13")
    assert word_hits(f"{WORD.capitalize()} 40 re-ran the campaign")
    token = "5b5" "572b"  # in two pieces, so that this file holds no hash-like token
    assert hash_hits(f"the code of commit {token}") == [token]
    assert hash_hits(f"at {token}: 560 passed") == [token]
    assert hash_hits(f'{{"commit": "{token}"}}') == [token]
    assert hash_hits("colour #1f77b4 of the plot") == []
    assert hash_hits("laspy==2.7.0 --hash=sha256:" + "ab12" * 16) == []
    assert hash_hits("the value of 1234567 points") == []  # no letter: a number
    assert hash_hits("a cafe and a decade") == []  # no digit: a word


def test_no_development_history_in_the_product():
    hits = scan()
    assert not hits, "development history in the product:\n" + "\n".join(hits)
