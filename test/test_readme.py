"""The README is a manual a newcomer can trust: every command it shows exists,
every file it names is there, and it stays short enough to read."""
import re
from pathlib import Path

from has_control.cli.main import COMMANDS, NODES

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()
#: Where the README points: files and folders of the repository it names.
PATH = re.compile(r"(?<![\w/.-])((?:docs|config|test|has_control|scripts|launch|\.ci)/[\w./-]*[\w/])")


def test_every_has_control_subcommand_it_shows_exists():
    shown = set(re.findall(r"has-control ([a-z][a-z-]*)", README))
    assert shown and shown <= set(COMMANDS) | set(NODES), sorted(shown - set(COMMANDS) - set(NODES))


def test_every_ros2_run_executable_it_shows_is_a_node():
    shown = set(re.findall(r"ros2 run has_control ([a-z_]+)", README))
    assert shown and shown <= set(NODES)


def test_every_path_it_names_exists():
    named = {p.rstrip("/.") for p in PATH.findall(README)}
    missing = sorted(p for p in named if not (ROOT / p).exists())
    assert named and missing == []


def test_every_local_link_resolves():
    links = re.findall(r"\]\(([^)#:]+)(?:#[^)]*)?\)", README)
    assert links and [link for link in links if not (ROOT / link).exists()] == []


def test_it_has_a_table_of_contents_that_matches_its_sections():
    sections = re.findall(r"^## (.+)$", README, re.M)
    anchors = re.findall(r"^\d+\. \[[^]]+\]\(#([^)]+)\)$", README, re.M)
    slug = {re.sub(r"[^\w\- ]", "", s).strip().lower().replace(" ", "-"): s for s in sections}
    assert anchors and all(a in slug for a in anchors)


def test_it_stays_a_manual():
    assert len(README.splitlines()) <= 350
    assert not re.search(r"issue #\d+", README)
