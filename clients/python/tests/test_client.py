"""ufops.Client against a running `ufops serve`: episodes equal the store's, label writes with
If-Match, and a stale write raises ConflictError saying who changed the label."""
from __future__ import annotations

import pytest

import ufops
from conftest import Server, Ufops, require, serving


def test_episodes_follow_every_page(server: Server, trained: Ufops) -> None:
    c = ufops.Client(server.url, server.token)
    eps = c.episodes(limit=7)  # 40 episodes in pages of 7
    cli = trained.json("episodes", "--json")
    assert [e["id"] for e in eps] == [e["id"] for e in cli]
    assert c.episodes_frame(checkpoint="ckpt-0").height == len(cli)
    # Over the API or from the store: one table, same columns and values.
    require("polars.testing").assert_frame_equal(c.episodes_frame(), ufops.Store(trained.data_dir).episodes())


def test_label_writes_and_conflicts(server: Server) -> None:
    c = ufops.Client(server.url, server.token)
    ep = c.episodes(limit=1)[0]
    rev = ep["label_revision"]
    first = c.set_label(ep["id"], "failure", rev, note="first look")
    assert first["revision"] == rev + 1
    # A second labeler who read the old revision loses, and learns who won.
    with pytest.raises(ufops.ConflictError) as info:
        c.set_label(ep["id"], "success", rev)
    e = info.value
    assert e.actor == "pytest" and e.revision == rev + 1 and e.label == "failure"
    assert "changed by pytest" in str(e)
    assert c.episode(ep["id"])["label"] == "failure"
    c.set_label(ep["id"], "success", rev + 1)


def test_bad_requests(server: Server) -> None:
    with pytest.raises(ufops.AuthError, match="401"):
        ufops.Client(server.url, "wrong").episodes()
    c = ufops.Client(server.url, server.token)
    with pytest.raises(ufops.NotFoundError, match="404"):
        c.episode("no-such-episode")
    with pytest.raises(ValueError, match="400"):
        c.set_label(c.episodes(limit=1)[0]["id"], "maybe", 0)
    with pytest.raises(ufops.FetchError):
        ufops.Client("http://127.0.0.1:9", "t", timeout=2).episodes()


def test_change_feed_follows_label_writes(server: Server) -> None:
    import threading

    c = ufops.Client(server.url, server.token)
    head = c.events(wait=0)["head"]
    ep = c.episodes(limit=1)[0]
    # A write from elsewhere while this client waits on the feed.
    writer = threading.Timer(0.3, lambda: c.set_label(ep["id"], "failure", ep["label_revision"]))
    writer.start()
    page = c.events(head, kinds=["label.set"], wait=20)
    writer.join()
    assert [(e["kind"], e["subject"]) for e in page["events"]] == [("label.set", ep["id"])]
    assert page["events"][0]["data"]["revision"] == ep["label_revision"] + 1
    assert page["next"] == page["events"][0]["seq"] > head
    # The generator resumes from a sequence number and yields each event once.
    c.set_label(ep["id"], "success", ep["label_revision"] + 1)
    followed = next(iter(c.follow_events(page["next"], kinds=["label.set"])))
    assert followed["data"]["label"] == "success" and followed["seq"] > page["next"]
    with pytest.raises(ValueError, match="400"):
        c.events(kinds=["no.such.kind"])


def test_automations_are_declared_listed_and_audited(server: Server, trained: Ufops) -> None:
    labeler = ufops.Client(server.url, server.token)
    with pytest.raises(ufops.AuthError, match="403"):
        labeler.create_automation("synth", "score_on_publish")
    with serving(trained, "trainer", name="pytest-trainer") as s:
        c = ufops.Client(s.url, s.token)
        head = c.events()["head"]
        a = c.create_automation("synth", "score_on_publish", {"checkpoint": "ckpt-0"})
        assert a["rule"] == "score_on_publish" and a["params"] == {"checkpoint": "ckpt-0"}
        assert [x["id"] for x in c.automations("synth")] == [a["id"]]
        with pytest.raises(ValueError, match="400"):
            c.create_automation("synth", "train_on_labels", {"min_labeled": 1})
        c.delete_automation(a["id"])
        assert c.automations() == []
        kinds = [(e["kind"], e["subject"]) for e in c.events(head, kinds=["automation.created", "automation.deleted"])["events"]]
        assert kinds == [("automation.created", a["id"]), ("automation.deleted", a["id"])]
