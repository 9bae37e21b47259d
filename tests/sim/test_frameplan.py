"""FramePlan.build (whole-frame numpy) against the per-cloth builder it replaced, kept here as
the reference only: every field and every static byte equal for random rosters (encodings,
normals, steps, ids of every length, singles and bundles in any order, cloths in no
publication), and the same refusals."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from drape.client import protocol as P
from drape.server.sim.opencl.frameplan import (
    HEADER_OFFSETS,
    ClothEntry,
    FramePlan,
    Publication,
    encode_layout,
    state_size,
)
from drape.server.sim.roster import Roster


def _reference_row(c: ClothEntry, state_at: int, bundle_at: int, index: int, entry_at: int) -> list[int]:
    W = encode_layout()
    row = [0] * W["ENC_ROW_WORDS"]
    row[W["ENC_ROW_VBASE"]] = c.vbase
    row[W["ENC_ROW_N"]] = c.n
    row[W["ENC_ROW_ENC"]] = c.encoding
    row[W["ENC_ROW_NORMALS"]] = int(c.normals)
    row[W["ENC_ROW_STATE"]] = state_at
    row[W["ENC_ROW_BUNDLE"]] = bundle_at
    row[W["ENC_ROW_CLOTH"]] = index
    if c.encoding == P.ENC_PREDICTIVE:
        row[W["ENC_ROW_ENTRY"]] = entry_at
        row[W["ENC_ROW_INVSTEP"]] = int(np.array(P.inverse_step(c.step), np.float32).view(np.uint32))
        row[W["ENC_ROW_HIST"]] = c.hbase if c.hbase >= 0 else c.vbase
    else:
        row[W["ENC_ROW_ENTRY"]] = W["ENC_NONE"]
    return row


def _reference(cloths: list[ClothEntry], publications: list[Publication]) -> dict[str, object]:
    """The per-cloth builder of protocol 1.8's first device encoder (commit c426692), its
    checks and its layout, one cloth at a time in Python."""
    k = len(cloths)
    for i, c in enumerate(cloths):
        if c.encoding not in P.ENCODING_NAMES:
            raise ValueError(f"cloth {i} ({c.cloth!r}): unknown encoding {c.encoding}")
        if c.encoding == P.ENC_PREDICTIVE and not P.STEP_RANGE[0] <= c.step <= P.STEP_RANGE[1]:
            raise ValueError(f"cloth {i} ({c.cloth!r}): step {c.step} out of {P.STEP_RANGE}")
        if c.vbase < 0 or c.n < 0 or c.vbase + c.n >= 2**32:
            raise ValueError(f"cloth {i} ({c.cloth!r}): bad vertex range {c.vbase}+{c.n}")
    owner = np.full(k, -1, np.int64)
    state_offset = np.full(k, -1, np.int64)
    pub_offset = np.zeros(len(publications), np.int64)
    pub_size = np.zeros(len(publications), np.int64)
    W = encode_layout()
    none = W["ENC_NONE"]
    rows: list[list[int]] = []
    parts: list[tuple[int, Publication]] = []
    at = 0
    for p, pub in enumerate(publications):
        idx = list(pub.cloths)
        if not idx:
            raise ValueError(f"publication {p} ({pub.key!r}) has no cloth")
        if not pub.bundle and len(idx) != 1:
            raise ValueError(f"single publication {p} ({pub.key!r}) has {len(idx)} cloths")
        for i in idx:
            if not 0 <= i < k:
                raise ValueError(f"publication {p} ({pub.key!r}) names cloth {i} of {k}")
            if owner[i] >= 0:
                raise ValueError(f"cloth {i} ({cloths[i].cloth!r}) is in publications {owner[i]} and {p}")
            owner[i] = p
            if pub.bundle and not P.valid_id(cloths[i].cloth):
                raise ValueError(f"bundle {pub.key!r}: invalid cloth id {cloths[i].cloth!r}")
        sizes = [state_size(cloths[i].n, cloths[i].encoding, cloths[i].normals) for i in idx]
        if pub.bundle:
            size = P.bundle_size((cloths[i].cloth, s) for i, s in zip(idx, sizes, strict=True))
            s_at = at + P.BUNDLE_HEADER_SIZE
            for j, (i, s) in enumerate(zip(idx, sizes, strict=True)):
                eh = P.bundle_entry_header_size(cloths[i].cloth)
                s_at += eh
                state_offset[i] = s_at
                be = s_at - eh + HEADER_OFFSETS["BE_SIZE"]
                rows.append(_reference_row(cloths[i], s_at, at if j == 0 else none, i, be))
                s_at += P.align8(s)
        else:
            size = sizes[0]
            state_offset[idx[0]] = at
            rows.append(_reference_row(cloths[idx[0]], at, none, idx[0], none))
        pub_offset[p], pub_size[p] = at, size
        parts.append((at, pub))
        at = P.align8(at + size)
    template = np.zeros(at, np.uint8)
    buf = memoryview(template).cast("B")  # type: ignore[arg-type]
    for off, pub in parts:
        if pub.bundle:
            P.pack_bundle_header(buf[off:], 0, 0, len(pub.cloths))
            for i in pub.cloths:
                c = cloths[i]
                e = int(state_offset[i]) - P.bundle_entry_header_size(c.cloth)
                P.pack_bundle_entry(buf, e, c.cloth, state_size(c.n, c.encoding, c.normals))
        for i in pub.cloths:
            c = cloths[i]
            so = int(state_offset[i])
            if c.encoding == P.ENC_PREDICTIVE:
                hs = P.PREDICTIVE_HEADER_SIZE
                P.pack_state_header(buf, so, c.encoding, 0, c.n, 0, 0, (0.0,) * 3, (0.0,) * 3, hs)
                P.PREDICTIVE_HEADER.pack_into(buf, so + P.STATE_HEADER_SIZE, float(np.float32(c.step)), 0, 1, 0, 0, 0)
            else:
                P.pack_state_header(buf, so, c.encoding, 0, c.n, 0, 0, (0.0,) * 3, (0.0,) * 3)
    table = np.array(rows, np.uint32).reshape(-1, W["ENC_ROW_WORDS"])
    enc_idx = table[:, W["ENC_ROW_CLOTH"]].astype(np.int64)
    ends = table[:, W["ENC_ROW_VBASE"]].astype(np.int64) + table[:, W["ENC_ROW_N"]]
    return {
        "pub_offset": pub_offset,
        "pub_size": pub_size,
        "state_offset": state_offset,
        "rows": table,
        "template": template,
        "max_n": int(table[:, W["ENC_ROW_N"]].max(initial=0)),
        "vertex_end": int(ends.max(initial=0)),
        "normals": bool(table[:, W["ENC_ROW_NORMALS"]].any()),
        "_bounds_at": state_offset[enc_idx] if len(enc_idx) else np.zeros(0, np.int64),
        "predictive": np.array([c.encoding == P.ENC_PREDICTIVE for c in cloths], bool),
        "owner": owner,
        "is_bundle": np.array([p.bundle for p in publications], bool),
        "_sizes": np.array([state_size(c.n, c.encoding, c.normals) for c in cloths], np.int64),
        "_pred_extra": np.array([P.PREDICTIVE_HEADER_SIZE + 6 * c.n * c.normals for c in cloths], np.int64),
    }


def _random_roster(rng: np.random.Generator, k: int) -> tuple[list[ClothEntry], list[Publication]]:
    chars = "abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789_.-"
    steps = [0.00025, 0.001, 0.0037, P.DEFAULT_STEP]
    cloths, vbase = [], int(rng.integers(0, 100))
    for i in range(k):
        length = int(rng.integers(1, 65))
        cid = "".join(rng.choice(list(chars), length)) + f"{i}"
        cid = cid[-64:]
        n = int(rng.choice([0, 1, 3, 31, 32, 33, 100, 1024]))
        enc = int(rng.choice(list(P.ENCODING_NAMES)))
        hbase = int(rng.integers(0, 2**20)) if rng.random() < 0.3 else -1  # a decimated streams' history
        cloths.append(ClothEntry(cid, vbase, n, enc, bool(rng.integers(0, 2)), float(rng.choice(steps)), hbase))
        vbase += n + int(rng.integers(0, 5))
    order = rng.permutation(k).tolist()
    pubs: list[Publication] = []
    while order:
        if rng.random() < 0.15:  # left out of every publication
            order.pop()
        elif rng.random() < 0.5:
            pubs.append(Publication(f"s/{len(pubs)}", (order.pop(),)))
        else:
            take = int(rng.integers(1, 12))
            members, order = order[:take], order[take:]
            pubs.append(Publication(f"b/{len(pubs)}", tuple(members), True))
    rng.shuffle(pubs)  # type: ignore[arg-type]
    return cloths, pubs


def _assert_same(plan: FramePlan, want: dict[str, object]) -> None:
    for name, value in want.items():
        got = getattr(plan, name)
        if isinstance(value, np.ndarray):
            assert got.dtype == value.dtype or got.dtype.kind == value.dtype.kind, name
            np.testing.assert_array_equal(got, value, err_msg=name)
        else:
            assert got == value, name
    assert plan.template.tobytes() == want["template"].tobytes()  # type: ignore[union-attr]


@pytest.mark.parametrize("seed", range(40))
def test_plan_equals_the_per_cloth_builder(seed):
    rng = np.random.default_rng(seed)
    cloths, pubs = _random_roster(rng, int(rng.integers(0, 60)))
    plan = FramePlan.build(cloths, pubs)
    _assert_same(plan, _reference(cloths, pubs))
    ref = _reference(cloths, pubs)
    np.testing.assert_array_equal(plan.time_offsets()[: len(plan.rows)], ref["_bounds_at"] + HEADER_OFFSETS["ST_TIME"])


def test_large_bundled_plan_equals_the_per_cloth_builder():
    """8192 predictive 32x32 cloths in bundles of 64 (issue 21's load), and the same with one gone."""
    cloths = [ClothEntry(f"c{i:05d}", 1024 * i, 1024, P.ENC_PREDICTIVE, False, 0.001) for i in range(8192)]
    pubs = [Publication(f"b/{j}", tuple(range(j, j + 64)), True) for j in range(0, 8192, 64)]
    _assert_same(FramePlan.build(cloths, pubs), _reference(cloths, pubs))
    pubs[5] = Publication("b/5", pubs[5].cloths[:-1], True)
    _assert_same(FramePlan.build(cloths, pubs), _reference(cloths, pubs))


def _bad_cases() -> list[tuple[list[ClothEntry], list[Publication]]]:
    a, b = ClothEntry("a", 0, 4), ClothEntry("b", 4, 4)
    return [
        ([a, b], [Publication("x", (0,)), Publication("y", (0, 1), True)]),
        ([a, b], [Publication("x", (0, 1))]),
        ([a], [Publication("x", (), True)]),
        ([a, b], [Publication("x", (2,))]),
        ([a, b], [Publication("x", (-1,))]),
        ([ClothEntry("a", 0, 4, 7)], [Publication("x", (0,))]),
        ([ClothEntry("a", 0, 4, P.ENC_PREDICTIVE, step=1.0)], [Publication("x", (0,))]),
        ([a, ClothEntry("bad id", 0, 4)], [Publication("x", (0, 1), True)]),
        ([a, ClothEntry("é", 0, 4)], [Publication("x", (1, 0), True)]),
        ([a, ClothEntry("x" * 65, 0, 4)], [Publication("x", (0,)), Publication("y", (1,), True)]),
        ([ClothEntry("a", -1, 4)], [Publication("x", (0,))]),
        ([a, b], [Publication("x", (1,)), Publication("y", (0, 0), True), Publication("z", ())]),
        ([a, b], [Publication("z", (0, 1, 1), True), Publication("y", (0,))]),
    ]


@pytest.mark.parametrize("case", range(len(_bad_cases())))
def test_bad_plans_are_refused_as_before(case):
    cloths, pubs = _bad_cases()[case]
    with pytest.raises(ValueError) as want:
        _reference(cloths, pubs)
    with pytest.raises(ValueError) as got:
        FramePlan.build(cloths, pubs)
    assert str(got.value) == str(want.value)


def test_an_id_two_cloths_share_is_refused():
    """Two cloths of one id in a frame (what test_predictive_frames_equal_the_host_encoder drew
    with DRAPE_TEST_SEED=20: "n" twice, one unwatched) would code two streams on the device (one
    per plan row) and one on the host (one per id: the unwatched cloth's forgetting restarted
    the other's, a keyframe where the device predicted) that no decoder could tell apart: the
    plan refuses it, from entries and from a roster alike."""
    cloths = [ClothEntry("n", 0, 4, P.ENC_PREDICTIVE), ClothEntry("m", 4, 4), ClothEntry("n", 8, 4, P.ENC_PREDICTIVE)]
    pubs = [Publication("x", (0,)), Publication("y", (2, 1), True)]
    with pytest.raises(ValueError, match=r"cloth 2 \('n'\): the id of cloth 0 too"):
        FramePlan.build(cloths, pubs)
    recs = [
        SimpleNamespace(id=c.cloth, key=f"k/{i}", encoding="predictive", step=1e-3, bundle_key=None)
        for i, c in enumerate(cloths)
    ]
    with pytest.raises(ValueError, match="the id of cloth 0 too"):
        FramePlan.for_roster(Roster.of((1, 0), recs, np.zeros(3, bool)), [0, 4, 8], [4, 4, 4])
    FramePlan.build([cloths[0], cloths[1], cloths[2]._replace(cloth="o")], pubs)  # distinct: fine


def test_a_bundle_may_hold_an_id_valid_only_by_the_protocol_s_own_check():
    """Ids are checked by P.valid_id (the one copy of the rule), whatever the fast check thinks."""
    c = ClothEntry("ok\n", 0, 4)
    pubs = [Publication("x", (0,), True)]
    if P.valid_id(c.cloth):
        _assert_same(FramePlan.build([c], pubs), _reference([c], pubs))
    else:
        with pytest.raises(ValueError, match="invalid cloth id"):
            FramePlan.build([c], pubs)


@pytest.mark.parametrize("seed", range(10))
def test_a_roster_s_plan_equals_the_plan_of_its_entries(seed):
    """FramePlan.for_roster (the tick thread's, from the roster's columns, its entries made only
    when asked for) == FramePlan.build of the same entries."""
    rng = np.random.default_rng(100 + seed)
    k = int(rng.integers(1, 50))
    recs = [
        SimpleNamespace(
            id=f"c{i}",
            key=f"k/c{i}",
            encoding=str(rng.choice(list(P.ENCODING_IDS))),
            step=float(rng.choice([1e-3, 4e-3])),
            bundle_key=[None, "b/0", "b/1"][int(rng.integers(0, 3))],
        )
        for i in range(k)
    ]
    normals = rng.random(k) < 0.5
    roster = Roster.of((1, 0), recs, normals)
    vbase = np.cumsum(rng.integers(0, 50, k)).tolist()
    counts = rng.integers(0, 40, k).tolist()
    plan = FramePlan.for_roster(roster, vbase, counts)
    entries = [
        ClothEntry(r.id, vb, n, P.ENCODING_IDS[r.encoding], bool(nr), r.step)
        for r, vb, n, nr in zip(recs, vbase, counts, normals, strict=True)
    ]
    pubs = [Publication(key, tuple(idx), b) for _, key, idx, b in roster.publications()]
    _assert_same(plan, _reference(entries, pubs))
    assert list(plan.cloths) == entries and plan.cloths[-1] == entries[-1] and plan.cloths[1:3] == entries[1:3]
    assert plan.ids == [e.cloth for e in entries]
    np.testing.assert_array_equal(plan.entry_header_sizes, [P.bundle_entry_header_size(e.cloth) for e in entries])


@pytest.mark.parametrize("seed", range(10))
def test_a_subset_equals_the_plan_of_its_entries(seed):
    """FramePlan.subset (devrates.py's decimated plans, from the plan's columns) == the per-cloth
    build devrates.py did before: the selected publications' cloths in row order, each with its
    history base, under new keys."""
    rng = np.random.default_rng(200 + seed)
    cloths, pubs = _random_roster(rng, int(rng.integers(1, 60)))
    plan = FramePlan.build(cloths, pubs)
    sel = sorted(rng.permutation(len(pubs))[: int(rng.integers(0, len(pubs) + 1))].tolist())
    keys = [f"{pubs[j].key}/every/2" for j in sel]
    idx = [i for j in sel for i in pubs[j].cloths]
    hb = rng.integers(0, 2**20, len(idx))
    sub, members = plan.subset(sel, keys, hb)
    np.testing.assert_array_equal(members, idx)
    entries, out = [], []
    for key, j in zip(keys, sel, strict=True):
        at = tuple(range(len(entries), len(entries) + len(pubs[j].cloths)))
        entries.extend([cloths[i]._replace(hbase=int(hb[a])) for a, i in zip(at, pubs[j].cloths, strict=True)])
        out.append(Publication(key, at, pubs[j].bundle))
    _assert_same(sub, _reference(entries, out))
    assert list(sub.cloths) == entries and sub.publications == out
    with pytest.raises(ValueError, match="ascending"):
        plan.members([1, 0] if len(pubs) > 1 else [0, 0])
