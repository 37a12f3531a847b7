"""The Foxglove layout shipped with the package: well formed, and every topic and field it plots exists in
the MCAP that ``replay --mcap`` writes (so a renamed topic or field fails here, not in front of a user)."""

from __future__ import annotations

import json
import re
from importlib import resources

import pytest
from mcap.reader import make_reader

from replay.cli import main
from tests.test_cli_replay import rec_dir  # noqa: F401  (the synthetic walk fixture)

LAYOUT = resources.files("pdr_mag.sinks").joinpath("foxglove_layout.json")


def _panel_ids(node):
    if isinstance(node, str):
        return [node]
    return _panel_ids(node["first"]) + _panel_ids(node["second"])


def _paths(layout):
    """(panel, topic, field or None) of every message path the layout reads."""
    out = []
    for pid, cfg in layout["configById"].items():
        for path in cfg.get("paths", []):
            topic, _, field = path["value"].partition(".")
            out.append((pid, topic, re.sub(r"\.@\w+$", "", field)))
        if "topicToRender" in cfg:
            out.append((pid, cfg["topicToRender"], None))
        for topic in cfg.get("topics", {}):
            out.append((pid, topic, None))
    return out


def _fields(schema) -> set[str]:
    text = schema.data.decode()
    if schema.encoding == "jsonschema":
        return set(json.loads(text).get("properties", {}))
    # ros2msg: "type name" lines of the first message definition
    main_def = text.split("=" * 80)[0]
    return {ln.split()[1] for ln in main_def.splitlines() if ln.strip() and not ln.lstrip().startswith("#")}


def test_layout_is_well_formed():
    layout = json.loads(LAYOUT.read_text(encoding="utf-8"))
    assert {"configById", "layout", "globalVariables", "userNodes", "playbackConfig"} <= set(layout)
    placed = set(_panel_ids(layout["layout"]))
    for cfg in layout["configById"].values():
        placed |= {tab["layout"] for tab in cfg.get("tabs", [])}
    assert placed == set(layout["configById"])  # every panel placed once, every placed panel configured
    assert all(re.fullmatch(r"[A-Za-z0-9]+![a-z]+", pid) for pid in placed)


def test_layout_reads_only_what_the_mcap_has(rec_dir, tmp_path):  # noqa: F811
    out = tmp_path / "o.mcap"
    assert main(["replay", str(rec_dir), "--mcap", str(out), "-q"]) == 0
    with out.open("rb") as fh:
        summary = make_reader(fh).get_summary()
    topics = {ch.topic: summary.schemas[ch.schema_id] for ch in summary.channels.values()}
    layout = json.loads(LAYOUT.read_text(encoding="utf-8"))
    missing = []
    for pid, topic, field in _paths(layout):
        if topic == "/reference/os/heading" or topic == "/reference/os/orientation":
            continue  # only recordings with the phone's own orientation have it (the synthetic walk does not)
        if topic not in topics:
            missing.append((pid, topic))
        elif field and field not in _fields(topics[topic]):
            missing.append((pid, f"{topic}.{field}"))
    assert missing == []


@pytest.mark.parametrize("name", ["Plot!heading", "StateTransitions!states", "RosOut!episodes"])
def test_panels_of_the_drift_story(name):
    layout = json.loads(LAYOUT.read_text(encoding="utf-8"))
    assert name in layout["configById"]
    assert layout["configById"]["RosOut!episodes"]["searchTerms"] == ["drift_episode"]
