"""The documentation is true to the repository (docs/index.md is the map).

* every repository path named in README.md and docs/**/*.md exists: ``torchfit/...``,
  ``tests/...``, ``scripts/...``, ``conf/...``, ``docs/...``, ``experiments/...``, and module
  paths inside the package such as ``run/fitting.py`` (a path followed by ``<``, ``*`` or
  ``{`` is a pattern, not a path). A lab note may name a file that is gone (history: "what
  moved"); such names are listed in :data:`HISTORY`, per note, and must really be gone;
* every relative markdown link resolves, its ``#anchor`` to a heading of the page;
* docs/index.md links every page under docs/;
* the layout table of docs/architecture.md lists exactly the packages of torchfit/
  (subpackages included) and its top-level modules, and its layer table states exactly the
  import rules tests/test_layers.py enforces;
* no file of the repository points outside it (to the design and problem pages that lived
  beside it, or to the directory that held them);
* docs/reference.md is what ``scripts/tools/reference.py`` writes from the faces now (each
  face's ``__all__`` and each name's first docstring sentence), as the layout table is
  checked against the packages.

Each check is a function of text, tested on a bad sample so that it can fail.
"""
from __future__ import annotations

import importlib.util
import re
import subprocess
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DOCS = REPO / "docs"
PACKAGE = REPO / "torchfit"

#: Names of files that are gone, named on purpose by a lab note (its history).
HISTORY: dict[str, set[str]] = {
    "docs/notes/structure.md": {"physics/equilibrium.py", "linalg/sparse_solve.py",
                                "mesh/arm.py", "problems/animation.py",
                                "linalg/backends.py", "mesh/tetrahedralize.py",
                                "problems/rigged_body.py"},
    "docs/notes/tensorboard.md": {"torchfit/logging/tensorboard.py"},
}

#: What no file may mention: pages outside the repository (spelt in pieces so that this
#: file does not mention them itself).
OUTSIDE = ("DESIGN" + ".md", "PROBLEMS" + ".md", "../" + "shared")

_TOP = r"(?:torchfit|tests|scripts|conf|docs|experiments)"
_LAYER = r"(?:linalg|mesh|physics|params|problems|solvers|reporting|run)"
_PATH = re.compile(rf"(?<![\w./<>-])({_TOP}/[\w./-]*|{_LAYER}/[\w./-]*(?:\.py|/))")
_LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")
_FENCE = re.compile(r"^```.*?^```", re.S | re.M)


def doc_pages() -> list[Path]:
    return [REPO / "README.md", *sorted(DOCS.rglob("*.md"))]


def named_paths(text: str) -> list[str]:
    """The repository paths a page names (trailing full stops dropped, patterns skipped)."""
    out = []
    for match in _PATH.finditer(text):
        if text[match.end():match.end() + 1] in ("<", "*", "{"):
            continue
        path = match.group(1).rstrip(".")
        if path.endswith(("/", ".py", ".md", ".sh", ".yaml", ".txt", ".npz", ".png")) or \
                "/" in path.rstrip("/"):
            out.append(path)
    return out


def path_exists(path: str, repo: Path = REPO) -> bool:
    """A path from the repository root, or a module path inside the package."""
    if re.match(_TOP + "/", path):
        return (repo / path).exists()
    return (repo / "torchfit" / path).exists()


def missing_paths(text: str, history: set[str] = frozenset(), repo: Path = REPO) -> list[str]:
    return sorted({p for p in named_paths(text) if p not in history and not path_exists(p, repo)})


def slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"[^\w\- ]", "", heading.strip().lower())
    return text.replace(" ", "-")


def anchors(text: str) -> set[str]:
    return {slug(line.lstrip("#")) for line in _FENCE.sub("", text).splitlines()
            if line.startswith("#")}


def links(text: str) -> list[str]:
    """Relative link targets of a page (outside code blocks; no URLs)."""
    return [t for t in _LINK.findall(_FENCE.sub("", text))
            if not re.match(r"[a-z]+:", t) and not t.startswith("#")]


def broken_links(page: Path, text: str) -> list[str]:
    bad = []
    for target in links(text):
        file, _, anchor = target.partition("#")
        resolved = (page.parent / file).resolve()
        if not resolved.exists():
            bad.append(target)
        elif anchor and resolved.suffix == ".md" and anchor not in anchors(resolved.read_text()):
            bad.append(target)
    return bad


def unlinked_pages(index: Path, text: str, pages: list[Path]) -> list[str]:
    linked = {(index.parent / t.partition("#")[0]).resolve() for t in links(text)}
    return sorted(str(p.relative_to(index.parent)) for p in pages
                  if p.resolve() != index.resolve() and p.resolve() not in linked)


def section(text: str, title: str) -> str:
    """The body of the ``## <title>`` section of a page."""
    match = re.search(rf"^## {re.escape(title)}\n(.*?)(?=^## |\Z)", text, re.S | re.M)
    assert match, f"no section '## {title}'"
    return match.group(1)


def table_rows(text: str) -> list[list[str]]:
    rows = []
    for line in text.splitlines():
        if line.startswith("|") and not re.match(r"\|\s*-", line):
            rows.append([cell.strip() for cell in line.strip().strip("|").split("|")])
    return rows[1:]     # without the header


def layout_paths(text: str) -> set[str]:
    """The paths the Layout table of docs/architecture.md lists (its first column)."""
    return {row[0].strip("`") for row in table_rows(section(text, "Layout"))
            if row[0].startswith("`torchfit/")}


def package_paths(package: Path = PACKAGE) -> set[str]:
    """Every package (``torchfit/x/``) and top-level module (``torchfit/x.py``) on disk."""
    root = package.parent
    packages = {f"{init.parent.relative_to(root).as_posix()}/" for init in
                package.rglob("__init__.py")}
    modules = {f"{p.relative_to(root).as_posix()}" for p in package.glob("*.py")
               if p.name != "__init__.py"}
    return packages | modules


def layer_rules(text: str, neutral: set[str]) -> dict[str, set[str]]:
    """The layer table of docs/architecture.md: layer -> the layers it may import."""
    rules = {}
    for row in table_rows(section(text, "Layers and the import rules")):
        allowed: set[str] = set()
        for name in re.findall(r"`(\w+)`", row[2]):
            allowed |= neutral if name == "neutral" else {name}
        rules[row[0].strip("`")] = allowed
    return rules


def enforced_rules() -> tuple[dict[str, set[str]], set[str]]:
    spec = importlib.util.spec_from_file_location("layer_rules", REPO / "tests" / "test_layers.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.ALLOWED, module.NEUTRAL


def reference_tool():
    """scripts/tools/reference.py as a module (it writes docs/reference.md)."""
    spec = importlib.util.spec_from_file_location("reference_tool",
                                                  REPO / "scripts" / "tools" / "reference.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def outside_references(text: str) -> list[str]:
    return [name for name in OUTSIDE if name in text]


def repository_files() -> list[Path]:
    """Tracked and untracked (not ignored) files; every file but .git and .venv without git."""
    try:
        listed = subprocess.run(["git", "-C", str(REPO), "ls-files", "--cached", "--others",
                                 "--exclude-standard", "-z"], capture_output=True, check=True)
        return [REPO / name for name in listed.stdout.decode().split("\0") if name]
    except (OSError, subprocess.CalledProcessError):
        skip = {".git", ".venv", "__pycache__", ".pytest_cache"}
        return [p for p in REPO.rglob("*") if p.is_file() and not skip & set(p.parts)]


#: ``docs/guide/formats.md#the-folder-format`` or ``docs/guide/formats.md ("The folder
#: format")``: a page of the documentation with a section, as code and messages name them
_DOC_POINTER = re.compile(r"(docs/[\w./-]+\.md)(?:#([\w-]+)|,? \(?(?:section )?\"([^\"]+)\")?")
#: the sources whose messages, docstrings and comments point into the documentation
POINTER_SOURCES = ("torchfit", "conf", "experiments", "scripts")


def broken_pointers(text: str, repo: Path = REPO) -> list[str]:
    """What a source file names of the repository that is not there: a path
    (:func:`missing_paths`), a section of a page (``#anchor`` or a quoted heading) that the
    page does not have."""
    bad = missing_paths(text, repo=repo)
    for match in _DOC_POINTER.finditer(text):
        page, anchor, heading = match.groups()
        target = repo / page
        if not target.is_file():
            continue                        # named by missing_paths already
        wanted = anchor or (slug(heading) if heading else None)
        if wanted and wanted not in anchors(target.read_text()):
            bad.append(match.group(0))
    return sorted(set(bad))


def pointer_sources() -> list[Path]:
    return sorted(p for d in POINTER_SOURCES for p in (REPO / d).rglob("*")
                  if p.suffix in (".py", ".yaml", ".sh") and "__pycache__" not in p.parts)


# -- the checks on the repository ---------------------------------------------------------
def test_every_pointer_in_the_code_and_configs_exists():
    """Messages, docstrings, comments and config comments point only to paths and sections
    of the documentation that exist (a refusal that names a section the guide lost is the
    TD's dead end)."""
    broken = {p.relative_to(REPO).as_posix(): bad for p in pointer_sources()
              if (bad := broken_pointers(p.read_text()))}
    assert not broken, f"pointers to what is not in the repository: {broken}"


def test_broken_pointers_finds_a_lost_page_and_a_lost_section(tmp_path):
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "guide.md").write_text("# Guide\n\n## The folder format\n")
    text = ('raise Error("see docs/guide.md#the-folder-format, docs/guide.md (\\"The folder '
            'format\\")")\n# docs/guide.md#bring-your-own-animation; docs/gone.md\n'
            "msg = 'docs/guide.md, section \"Bring your own\"'\n")
    text = text.replace("\\", "")
    assert broken_pointers(text, tmp_path) == [
        "docs/gone.md", "docs/guide.md#bring-your-own-animation",
        'docs/guide.md, section "Bring your own"']

def test_every_named_path_exists():
    missing = {}
    for page in doc_pages():
        name = page.relative_to(REPO).as_posix()
        found = missing_paths(page.read_text(), HISTORY.get(name, set()))
        if found:
            missing[name] = found
    assert not missing, f"paths named but not in the repository: {missing}"


def test_history_names_only_what_is_gone_and_still_named():
    for name, gone in HISTORY.items():
        text = (REPO / name).read_text()
        assert not [p for p in gone if path_exists(p)], f"{name}: these exist, drop them"
        assert gone <= set(named_paths(text)), f"{name} no longer names {gone - set(named_paths(text))}"


def test_every_relative_link_resolves():
    broken = {page.relative_to(REPO).as_posix(): bad for page in doc_pages()
              if (bad := broken_links(page, page.read_text()))}
    assert not broken, f"broken links: {broken}"


def test_the_index_links_every_page():
    index = DOCS / "index.md"
    missing = unlinked_pages(index, index.read_text(), sorted(DOCS.rglob("*.md")))
    assert not missing, f"docs/index.md does not link {missing}"


def test_the_layout_table_lists_exactly_the_packages():
    listed = layout_paths((DOCS / "architecture.md").read_text())
    actual = package_paths()
    assert listed == actual, (f"not in docs/architecture.md's Layout: {sorted(actual - listed)}; "
                              f"listed but not there: {sorted(listed - actual)}")


def test_the_layer_table_states_the_enforced_rules():
    allowed, neutral = enforced_rules()
    stated = layer_rules((DOCS / "architecture.md").read_text(), neutral)
    assert stated == allowed


def test_the_reference_is_what_the_faces_offer():
    tool = reference_tool()
    assert (DOCS / "reference.md").read_text() == tool.page(), \
        "docs/reference.md is stale: run .venv/bin/python scripts/tools/reference.py"


def test_nothing_points_outside_the_repository():
    found = {}
    for path in repository_files():
        if path.is_file():
            names = outside_references(path.read_bytes().decode("utf-8", "replace"))
            if names:
                found[path.relative_to(REPO).as_posix()] = names
    assert not found, found


# -- each check can fail --------------------------------------------------------------------
def test_missing_paths_finds_what_is_not_there():
    text = ("See `torchfit/run/fitting.py`, run/fitting.py, `docs/guide/nowhere.md`, "
            "(scripts/bench/gone.py) and mesh/nothing.py; tests/<layer>/test_<module>.py is "
            "a pattern, frames/*.obj is not a repository path.")
    assert missing_paths(text) == ["docs/guide/nowhere.md", "mesh/nothing.py",
                                   "scripts/bench/gone.py"]
    assert missing_paths(text, {"mesh/nothing.py", "docs/guide/nowhere.md",
                                "scripts/bench/gone.py"}) == []


def test_broken_links_finds_files_and_anchors_that_are_not_there():
    page = DOCS / "index.md"
    text = ("[ok](architecture.md) [ok too](index.md#lab-notes) [web](https://example.org) "
            "[gone](guide/nowhere.md) [no heading](index.md#no-such-heading)\n"
            "```\n[in code](ignored.md)\n```\n")
    assert broken_links(page, text) == ["guide/nowhere.md", "index.md#no-such-heading"]


def test_unlinked_pages_finds_a_page_the_index_leaves_out():
    pages = [DOCS / "index.md", DOCS / "architecture.md", DOCS / "problems.md"]
    assert unlinked_pages(DOCS / "index.md", "[a](architecture.md)", pages) == ["problems.md"]


def test_layout_check_finds_a_missing_and_an_extra_package(tmp_path):
    for sub in ("pkg", "pkg/sub", "pkg/sub/deeper"):
        (tmp_path / sub).mkdir()
        (tmp_path / sub / "__init__.py").write_text("")
    (tmp_path / "pkg" / "module.py").write_text("")
    (tmp_path / "pkg" / "sub" / "inner.py").write_text("")
    assert package_paths(tmp_path / "pkg") == {"pkg/", "pkg/sub/", "pkg/sub/deeper/",
                                               "pkg/module.py"}
    table = ("## Layout\n\n| path | job |\n| --- | --- |\n| `torchfit/` | all |\n"
             "| `torchfit/gone/` | a package that moved |\n| `torchfit/errors.py` | errors |\n")
    assert layout_paths(table) == {"torchfit/", "torchfit/gone/", "torchfit/errors.py"}
    assert layout_paths(table) != package_paths()


def test_layer_table_check_finds_a_wrong_rule():
    allowed, neutral = enforced_rules()
    text = (DOCS / "architecture.md").read_text()
    wrong = text.replace("| `neutral`, `linalg` |", "| `neutral`, `linalg`, `physics` |", 1)
    assert wrong != text
    assert layer_rules(wrong, neutral) != allowed


def test_outside_references_finds_each_name():
    for name in OUTSIDE:
        assert outside_references(f"see {name} for the rest") == [name]
    assert outside_references("see docs/architecture.md and docs/problems.md") == []


def test_the_reference_follows_a_face_to_its_definitions(tmp_path):
    tool = reference_tool()
    root = tmp_path / "torchfit"
    (root / "part").mkdir(parents=True)
    (root / "__init__.py").write_text('"""The package."""\nfrom .part import Thing\n'
                                      '__all__ = ["Thing"]\n')
    (root / "part" / "__init__.py").write_text(
        '"""A part: its job."""\nfrom .inner import LIMIT, Thing, use\n'
        '__all__ = ["LIMIT", "Thing", "use"]\n')
    (root / "part" / "inner.py").write_text(
        '"""Inner."""\n#: the largest size | ever\nLIMIT = 3\n\n\nclass Thing:\n'
        '    """A :class:`~torchfit.part.Thing` of ``size`` things. More here."""\n\n\n'
        'def use():\n    pass\n')
    (root / "errors.py").write_text('"""Errors."""\nclass Bad(Exception):\n    """Bad."""\n'
                                    '_hidden = 1\n')
    text = tool.page(tool.Source(root))
    assert "## `torchfit`\n\nThe package.\n" in text
    assert "| `Thing` | `torchfit.part.inner` | A `Thing` of `size` things. |" in text
    assert "| `LIMIT` | `torchfit.part.inner` | the largest size \\| ever |" in text
    assert "| `use` | `torchfit.part.inner` |  |" in text
    assert "## `torchfit.errors`" in text and "| `Bad` | `torchfit.errors` | Bad. |" in text
    assert "_hidden" not in text
    assert text.index("## `torchfit`\n") < text.index("## `torchfit.part`") < text.index(
        "## `torchfit.errors`")
    (root / "part" / "__init__.py").write_text('"""A part."""\nfrom .inner import use\n'
                                               '__all__ = ["use"]\n')
    assert tool.page(tool.Source(root)) != text         # a face that changes changes the page
