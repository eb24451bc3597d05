"""The bridge's name table (swarm.core.bridge.names): names and ids learnt, conflicts, stale
mappings giving way, and who is told of a conflict. A pure core: a manual clock."""

from __future__ import annotations

from swarm.core.bridge.names import NameTable, conflict_note
from swarm.core.wire.message_types import NameConflict


def test_a_pair_is_learnt_and_refreshed() -> None:
    t = NameTable("gcs", 255)
    assert t.learn("alpha", 3, 1.0) is None
    assert t.learn("alpha", 3, 50.0) is None  # the same claim again
    assert t.id_of("alpha") == 3 and t.name_of(3) == "alpha"
    assert t.as_dict() == {"gcs": 255, "alpha": 3}
    assert t.id_of("nobody") is None and t.name_of(9) is None


def test_a_name_under_another_id_is_a_conflict_naming_the_first_claimant() -> None:
    t = NameTable("gcs", 255)
    t.learn("alpha", 3, 0.0)
    assert t.learn("alpha", 4, 10.0) == 3
    assert t.id_of("alpha") == 3 and t.name_of(4) is None  # nothing changed


def test_an_id_under_another_name_is_a_conflict() -> None:
    t = NameTable("gcs", 255)
    t.learn("alpha", 3, 0.0)
    assert t.learn("bravo", 3, 10.0) == 3
    assert t.name_of(3) == "alpha"


def test_a_stale_mapping_gives_way_to_the_new_claim() -> None:
    t = NameTable("gcs", 255)
    t.learn("alpha", 3, 0.0)
    assert t.learn("alpha", 4, 30.5) is None  # not heard for more than 30 s
    assert t.id_of("alpha") == 4 and t.name_of(3) is None


def test_one_fresh_mapping_among_the_clashes_keeps_the_conflict() -> None:
    t = NameTable("gcs", 255)
    t.learn("alpha", 3, 0.0)
    t.learn("bravo", 4, 25.0)
    assert t.learn("alpha", 4, 40.0) == 3  # alpha is stale, bravo (id 4) is not
    assert t.id_of("alpha") == 3 and t.name_of(4) == "bravo"


def test_the_own_pair_never_goes_stale() -> None:
    t = NameTable("agent7", 7)
    assert t.learn("agent7", 9, 1e9) == 7
    assert t.learn("other", 7, 1e9) == 7
    assert t.id_of("agent7") == 7


def test_a_conflict_is_told_to_both_claimants_but_never_to_ourselves() -> None:
    told = conflict_note(5, "alpha", 3, 4)
    assert told == (NameConflict(5, "alpha", 4), [3, 4])
    # a frame from another radio under our own id: the claimant is us, told by our inbox only
    assert conflict_note(5, "agent5", 5, None) == (NameConflict(5, "agent5", 5), [])


def test_a_ground_station_and_ids_that_are_no_agents_tell_nobody() -> None:
    assert conflict_note(255, "alpha", 3, 4) is None
    assert conflict_note(5, "gcs", 255, None) is None
    note, targets = conflict_note(5, "alpha", 3, 254) or (None, [])
    assert note == NameConflict(5, "alpha", 3) and targets == [3]
