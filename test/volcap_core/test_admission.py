"""Admission: every stage keeps the same frame sets, whatever order or offsets the stamps come in."""
import random

import numpy as np
import pytest

from volcap_core.admission import Admission, AdmissionController, AdmissionRule

PERIOD = 33_333_333


def rig_stamps(sets, cameras=8, depth_offset_ns=12_000_000, jitter_ns=2_000_000, drift=0.0, seed=0, t0=10**18):
    """(camera, stream, stamp, set index) as vendor drivers send them: colour and depth stamped
    apart, per-camera jitter, optionally a clock running ``drift`` fast."""
    rng = random.Random(seed)
    out = []
    for k in range(sets):
        base = t0 + int(k * PERIOD * (1 + drift))
        for c in range(cameras):
            out.append((c, 'color', base + rng.randint(-jitter_ns, jitter_ns), k))
            out.append((c, 'depth', base + depth_offset_ns + rng.randint(-jitter_ns, jitter_ns), k))
    return out


def test_rule_round_trips_and_rejects_bad_text():
    rule = AdmissionRule(every=3, origin_ns=5, period_ns=PERIOD, since_ns=7)
    assert AdmissionRule.from_text(rule.to_text()) == rule
    for bad in ('not json', '[1]', '{"every": 2}', '{"every": "2", "origin_ns": 0, "period_ns": 1, "since_ns": 0}'):
        with pytest.raises(ValueError):
            AdmissionRule.from_text(bad)
    with pytest.raises(ValueError):
        AdmissionRule(every=0)


def test_controller_rule_admits_whole_sets_in_every_stage():
    """Stages that receive the stamps in different orders keep the same frame sets, each whole,
    through three changes of the decimation (1 -> 2 -> 3 -> 5)."""
    ctrl = AdmissionController(hold_s=0.0, calm_s=1e9)
    stamps = rig_stamps(300)
    rules = []
    for cam, stream, stamp, k in stamps:
        ctrl.observe((cam, stream), stamp)
        if cam == stream == 0 or (cam == 0 and stream == 'color' and k % 30 == 0 and k):
            rule = ctrl.step(k / 30, trouble=k <= 90)
            if rule is not None:
                rules.append(rule)
    assert [r.every for r in rules] == [2, 3, 5]
    stages = [Admission() for _ in range(3)]
    kept = []
    for n, stage in enumerate(stages):
        for rule in rules:
            stage.update(rule)
        order = list(stamps)
        random.Random(n).shuffle(order)
        kept.append({(c, st, k) for c, st, stamp, k in order if stage.admit((c, st), stamp)})
    assert kept[0] == kept[1] == kept[2]
    per_set = {}
    for _, _, k in kept[0]:
        per_set[k] = per_set.get(k, 0) + 1
    assert set(per_set.values()) == {16}        # whole: every camera's colour and depth
    last = rules[-1].since_ns + 20_000_000
    after = {k for c, st, stamp, k in stamps if stamp >= last}
    assert len(after & set(per_set)) == pytest.approx(len(after) / 5, abs=1)
    in_order = Admission()
    for rule in rules:
        in_order.update(rule)
    assert {(c, st, k) for c, st, stamp, k in stamps if in_order.admit((c, st), stamp)} == kept[0]
    assert in_order.missed == 0


def test_grid_follows_a_drifting_clock():
    """A camera clock 0.1 % fast leaves the grid by a third of a period in 10 s; re-anchoring keeps
    every set whole."""
    ctrl = AdmissionController(hold_s=0.0, calm_s=1e9)
    stage = Admission()
    stamps = rig_stamps(900, cameras=2, drift=0.001)
    ctrl.observe((0, 'color'), stamps[0][2])
    for cam, stream, stamp, k in stamps:
        ctrl.observe((cam, stream), stamp)
        if k % 30 == 0 and cam == 0 and stream == 'color':
            rule = ctrl.step(k / 30, trouble=k == 60)
            if rule is not None:
                stage.update(rule)
    assert ctrl.rule.every == 2 and len(stage.rules) > 2     # re-anchored along the way
    kept = {}
    for cam, stream, stamp, k in stamps:
        if stage.admit((cam, stream), stamp):
            kept.setdefault(k, set()).add((cam, stream))
    assert all(len(v) == 4 for v in kept.values())
    assert stage.missed == 0
    # re-anchoring keeps the turn: once one set in 2 is admitted, exactly every other set
    first = min(r.since_ns for r in stage.rules if r.every == 2)
    switched = [k for k in sorted(kept) if stamps[4 * k][2] > first]
    assert len(switched) > 300 and set(np.diff(switched)) == {2}


def test_missed_counts_admitted_frames_that_never_arrived():
    stage = Admission()
    stage.update(AdmissionRule(every=2, origin_ns=0, period_ns=PERIOD, since_ns=0))
    for k in (0, 2, 4, 10, 12):      # 6 and 8 lost upstream
        assert stage.admit('depth', k * PERIOD + 1000)
    assert stage.admit('depth', 3 * PERIOD) is False
    assert stage.counts() == {'admitted': 5, 'not_admitted': 1, 'missed': 2, 'admit_every': 2}


def test_calm_steps_down_only_with_cpu_headroom():
    ctrl = AdmissionController(hold_s=0.0, calm_s=2.0)
    for k in range(40):
        ctrl.observe('cam0', 10**18 + k * PERIOD)
    ctrl.step(0.0, trouble=True)
    ctrl.step(1.0, trouble=True)
    assert ctrl.rule.every == 3
    assert ctrl.step(5.0, trouble=False, cpu_busy=0.7) is None      # 0.7 * 3/2 > 0.85
    rule = ctrl.step(8.0, trouble=False, cpu_busy=0.5)
    assert rule is not None and rule.every == 2
    for t in (9.0, 10.0, 11.0):                       # up to 1/8 in trouble
        ctrl.step(t, trouble=True)
    assert ctrl.rule.every == 8
    assert ctrl.step(12.0, trouble=False, cpu_busy=0.2) is None          # calm from now
    assert ctrl.step(14.0, trouble=False, cpu_busy=0.2).every == 5      # far from the limit: a third fewer
    assert ctrl.step(17.0, trouble=False, cpu_busy=0.6).every == 4      # 0.6 * 5/3 > 0.85: one fewer
