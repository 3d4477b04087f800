"""``ros__parameters`` files read as rcl reads them: sections matched to nodes
(``/**``, ``*``, ``**``), keys flattened to dotted parameter names."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Iterable, Mapping

from has_control.common.errors import ConfigError, shown
from has_control.common.files import MiB, read_text
from has_control.config.yaml_safe import flatten, load_yaml

MAX_CONFIG_BYTES = 1 * MiB          # a parameter file [bytes]


#: The nodes whose sections the library (one process, one model) reads from a params file.
LIBRARY_NODES = ("/plant", "/controller", "/tuner")


def node_matches(pattern: str, node: str) -> bool:
    """Does the params-file section ``pattern`` apply to the node with fully
    qualified name ``node``, as rcl decides: ``/**`` matches every node, ``*``
    one name token, ``**`` any number of them, and a name without a leading
    ``/`` is a node in the root namespace."""
    pat = [t for t in ("/" + pattern.lstrip("/")).split("/")[1:]]
    name = node.strip("/").split("/") if node.strip("/") else []

    def match(i: int, j: int) -> bool:
        if i == len(pat):
            return j == len(name)
        if pat[i] == "**":
            return any(match(i + 1, k) for k in range(j, len(name) + 1))
        return j < len(name) and (pat[i] == "*" or pat[i] == name[j]) and match(i + 1, j + 1)
    return match(0, 0)


def read_parameter_file(path: str | Path, node: str | None = None) -> dict[str, Any]:
    """Flat parameters of one ``ros__parameters`` file for ``node`` (its fully
    qualified name), honouring section names as rcl does: a section applies
    to the nodes it matches (:func:`node_matches`), in file order.

    Without ``node`` (the library, which runs plant, controller and tuner in
    one process with one model) the sections of any of :data:`LIBRARY_NODES`
    apply, and a key that two of them set differently is refused naming
    both. A file without any ``ros__parameters`` section is an error. Only a
    regular UTF-8 file of at most :data:`MAX_CONFIG_BYTES` is read.
    """
    path = Path(path)
    doc = load_yaml(read_text(path, MAX_CONFIG_BYTES, ConfigError), str(path))
    if not isinstance(doc, Mapping):
        raise ConfigError(f"{path}: expected a mapping of node names to ros__parameters")
    targets = (node,) if node else LIBRARY_NODES
    per_node: dict[str, dict[str, Any]] = {t: {} for t in targets}
    setter: dict[tuple[str, str], str] = {}
    for section, body in doc.items():
        if not isinstance(body, Mapping) or "ros__parameters" not in body:
            raise ConfigError(f"{path}: section '{section}' has no ros__parameters")
        params = body["ros__parameters"]
        if params is None:
            continue
        if not isinstance(params, Mapping):
            raise ConfigError(f"{path}: {section}.ros__parameters is not a mapping")
        flat = flatten(params, where=f"{path}: {section}.ros__parameters")
        for t in targets:
            if node_matches(str(section), t):
                per_node[t].update(flat)
                setter.update({(t, k): str(section) for k in flat})
    if node:
        return per_node[node]
    merged: dict[str, Any] = {}
    for k in dict.fromkeys(k for t in targets for k in per_node[t]):
        owners = [t for t in _owners(k) if k in per_node[t]] or [t for t in targets if k in per_node[t]]
        first = owners[0]
        for other in owners[1:]:
            if per_node[other][k] != per_node[first][k]:
                raise ConfigError(
                    f"{path}: {k} = {shown(per_node[first][k])} for {first} (section {setter[(first, k)]}) but "
                    f"{shown(per_node[other][k])} for {other} (section {setter[(other, k)]}): the library runs "
                    "plant and controller on one model; give both the same value")
        merged[k] = per_node[first][k]
    return merged


def _owners(key: str) -> tuple[str, ...]:
    """The library nodes whose value of ``key`` the library takes (more than one: they must agree)."""
    if key.startswith(("actuator.", "simulation.")):
        return ("/plant", "/controller")
    if key.startswith("plant."):
        return ("/plant",)
    if key.startswith(("gains.", "adaptation.", "reference.", "noise.")):
        return ("/controller",)
    return ("/tuner",)


def read_parameter_files(files: Iterable[str | Path]) -> tuple[dict[str, Any], dict[str, str]]:
    """Flat parameters of several files, later ones winning, and the file each key came from."""
    flat: dict[str, Any] = {}
    sources: dict[str, str] = {}
    for f in files:
        for key, value in read_parameter_file(f).items():
            flat[key] = value
            sources[key] = str(f)
    return flat, sources
