"""Registration apart from the step (cerpe.algorithm.registrar, cerpe.algorithm.late): the worker's
queue and restarts, estimates that land late carried to the current frame, the synchronous path
untouched, the gate's scores of all peers at once, and the per-step request limit."""
from __future__ import annotations

import threading
from collections import Counter

import numpy as np
import pytest

from cerpe.algorithm import AlgorithmConfig, RegistrationJob, RegistrationResult, Team, WorkerRegistrar
from cerpe.algorithm.gating import cosines
from cerpe.geometry import e_pos, e_rot
from cerpe.memory import cosine
from cerpe.protocols import BackboneOutput
from gt_backbone import GTBackbone, OverlapDescriptor, SensorDepthDouble, make_world

CFG = AlgorithmConfig().override({"scale.min_pixels": 20})


class _Fake:
    """A backbone double: ``infer`` returns a marker output after ``hook(step)``."""

    def __init__(self, hook=None) -> None:
        self.hook, self.calls = hook, []

    def infer(self, views):
        step = views[0]
        self.calls.append(step)
        if self.hook is not None:
            self.hook(step)
        return BackboneOutput(T_frame_cam=np.tile(np.eye(4), (1, 1, 1)), valid=np.ones(1, bool),
                              depth=[np.zeros((2, 2))], depth_conf=[np.zeros((2, 2))], intrinsics=[None])


def _job(step: int) -> RegistrationJob:
    return RegistrationJob(step, [step])  # the double reads the step from the views


def test_worker_runs_jobs_and_counts_failures():
    def hook(step):
        if step == 2:
            raise ValueError("no")

    reg = WorkerRegistrar(_Fake(hook))
    for t in (1, 2, 3):
        assert reg.submit(_job(t)) == []
        assert reg.wait(10)
    got = reg.landed()
    assert [r.step for r in got] == [1, 2, 3]
    assert [r.out is None for r in got] == [False, True, False] and "ValueError" in got[1].error
    st = reg.stats()
    assert (st["submitted"], st["done"], st["failed"], st["dropped"], st["restarts"]) == (3, 2, 1, 0, 0)
    assert reg.landed() == []  # handed out once
    reg.close()


@pytest.mark.skipif(not hasattr(threading, "get_native_id") or not hasattr(__import__("os"), "getpriority"),
                    reason="per-thread niceness is Linux's")
def test_worker_runs_nicer_than_the_step():
    """The worker thread lowers its own priority (the step's thread keeps its own)."""
    import os

    from cerpe.algorithm.registrar import WORKER_NICE

    seen = {}
    main = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    reg = WorkerRegistrar(_Fake(lambda step: seen.setdefault(
        "nice", os.getpriority(os.PRIO_PROCESS, threading.get_native_id()))))
    reg.submit(_job(1))
    assert reg.wait(10)
    reg.close()
    assert seen["nice"] == min(main + WORKER_NICE, 19) and (seen["nice"] > main or main == 19)
    assert os.getpriority(os.PRIO_PROCESS, threading.get_native_id()) == main


def test_worker_shortens_the_thread_switch_interval():
    """The step waits for the GIL at most WORKER_SWITCH_S between two calls while the worker runs."""
    import sys

    from cerpe.algorithm.registrar import WORKER_SWITCH_S

    before = sys.getswitchinterval()
    try:
        sys.setswitchinterval(0.005)
        reg = WorkerRegistrar(_Fake())
        reg.submit(_job(1))
        assert reg.wait(10)
        reg.close()
        assert sys.getswitchinterval() == pytest.approx(WORKER_SWITCH_S)
        sys.setswitchinterval(0.0001)  # a shorter one set by the program stays
        reg = WorkerRegistrar(_Fake())
        reg.submit(_job(1))
        assert reg.wait(10)
        reg.close()
        assert sys.getswitchinterval() == pytest.approx(0.0001)
    finally:
        sys.setswitchinterval(before)


def test_full_queue_drops_the_oldest_job_counted():
    release, started = threading.Event(), threading.Event()

    def hook(step):
        if step == 1:
            started.set()
            release.wait(10)

    reg = WorkerRegistrar(_Fake(hook), queue_size=2)
    reg.submit(_job(1))
    assert started.wait(10)  # job 1 runs, the queue is empty
    assert reg.submit(_job(2)) == [] and reg.submit(_job(3)) == []
    dropped = reg.submit(_job(4))
    assert [j.step for j in dropped] == [2]
    release.set()
    assert reg.wait(10)
    assert [r.step for r in reg.landed()] == [1, 3, 4]
    assert reg.stats()["dropped"] == 1
    reg.close()


@pytest.mark.filterwarnings("ignore::pytest.PytestUnhandledThreadExceptionWarning")
def test_a_dead_worker_is_restarted_and_counted():
    def hook(step):
        if step == 1:
            raise SystemExit  # escapes the worker's loop: the thread ends

    reg = WorkerRegistrar(_Fake(hook))
    reg.submit(_job(1))
    reg._thread.join(10)
    assert not reg._thread.is_alive()
    reg.submit(_job(2))  # finds the worker dead: starts it again, job 1 is lost
    assert reg.wait(10)
    assert [r.step for r in reg.landed()] == [2]
    st = reg.stats()
    assert (st["restarts"], st["lost"], st["done"]) == (1, 1, 1)
    reg.close()


class DelayedRegistrar:
    """A registrar double that runs each job at once and hands its result out ``delay`` steps later
    (``landed`` is called once per step): deterministic lateness."""

    def __init__(self, backbone, delay: int) -> None:
        self.backbone, self.delay, self.queue, self.calls = backbone, delay, [], 0

    def submit(self, job):
        self.queue.append((self.calls + self.delay, RegistrationResult(job.step, self.backbone.infer(list(job.views)),
                                                                       submitted_s=job.submitted_s)))
        return []

    def landed(self):
        self.calls += 1
        out = [r for due, r in self.queue if due < self.calls]
        self.queue = [(due, r) for due, r in self.queue if due >= self.calls]
        return out

    def stats(self):
        return {}

    def close(self):
        pass


def _run(world, registrar=None):
    team = Team(world.robot_ids, OverlapDescriptor(world), GTBackbone(world, seed=1), SensorDepthDouble(), CFG,
                registrar=registrar)
    return team, list(team.run_encounter(world.to_encounter()))


@pytest.mark.parametrize("delay", [0, 2])
def test_late_estimates_are_carried_to_the_current_frame(delay):
    """With exact odometry a registration carried forward is exact; it lands ``delay`` steps late."""
    world = make_world(2, 40, seed=1)
    team, results = _run(world, lambda bb: DelayedRegistrar(bb, delay))
    direct = Counter()
    for res in results:
        for p in res.pairs:
            if p.source == "direct":
                direct[res.step] += 1
                gt = world.gt_T_cj_ci(res.step, world.index(p.ego), world.index(p.other))
                assert e_pos(p.T_cj_ci[:3, 3], gt[:3, 3]) < 1e-5 and e_rot(p.T_cj_ci, gt) < 1e-6
                assert ("registration-late" in p.reason) == (delay > 0)
            if res.step == 5:  # requested now, lands later: the pair waits
                assert p.source == "none" and "registration-pending" in p.reason or delay == 0
    # the gate is open at steps 5-9 and 25-29: their estimates land `delay` steps later
    assert sorted(direct) == [t + delay for w in ((5, 10), (25, 30)) for t in range(*w)]
    lateness = [s for a in team.agents for s, _ in a.s.registration_lateness]
    assert set(lateness) == {delay} and len(lateness) == 2 * 10


def test_without_a_registrar_the_step_is_algorithm_1():
    """No registrar: the received images are in the step's joint pass; every estimate lands at its step."""
    world = make_world(2, 40, seed=1)
    seen = []
    bb = GTBackbone(world, seed=1)
    infer = bb.infer

    def spy(views):
        seen.append(sum(v.role == "collaborator" for v in views))
        return infer(views)

    bb.infer = spy
    team = Team(world.robot_ids, OverlapDescriptor(world), bb, SensorDepthDouble(), CFG)
    results = list(team.run_encounter(world.to_encounter()))
    assert max(seen) == 1 and all(not a.s.pending and not a.s.registration_lateness for a in team.agents)
    assert {res.step for res in results for p in res.pairs if p.source == "direct"} == set(range(5, 10)) | set(range(25, 30))


def test_scores_of_all_peers_equal_the_per_pair_cosines():
    rng = np.random.default_rng(0)
    rows = [rng.standard_normal(300).astype(np.float32) for _ in range(6)] + [np.zeros(300, np.float32)]
    cols = [rng.standard_normal(300).astype(np.float32) for _ in range(5)]
    got = cosines(rows, cols)
    want = np.array([[cosine(r, c) for c in cols] for r in rows])
    np.testing.assert_allclose(got[:-1], want[:-1], rtol=0, atol=1e-12)
    assert np.isnan(got[-1]).all() and np.isnan(want[-1]).all()


def test_gate_scores_all_peers_as_one_at_a_time():
    """score_descriptors of all peers = score_descriptor peer by peer (scores, best keyframe), and = the
    loop over keyframes it replaces."""
    world = make_world(4, 12, seed=3)
    team, _ = _run(world)
    a = team.agents[0]
    rng = np.random.default_rng(1)
    dim = a.s.cur.descriptor.size
    got = {f"p{k}": rng.standard_normal(dim).astype(np.float32) for k in range(5)}
    got["lost"], got["zero"] = None, np.zeros(dim, np.float32)
    a.s.cur.scores.clear()
    batch = a.score_descriptors(got)
    mem = dict(a.s.cur.memory_scores)
    a.s.cur.scores.clear()
    one = {p: a.score_descriptor(p, d) for p, d in got.items()}
    assert repr(batch) == repr(one) and mem == a.s.cur.memory_scores
    own = a.s.cur.wire_descriptor
    for p in (f"p{k}" for k in range(5)):
        best = (cosine(own, got[p]), -1)
        for kf in a.memory.newest_first():
            c = cosine(kf.descriptor, got[p])
            if c > best[0]:
                best = (c, kf.step)
        assert batch[p] == pytest.approx(cosine(own, got[p]), abs=1e-12)
        assert mem[p][1] == best[1] and mem[p][0] == pytest.approx(best[0], abs=1e-12)
    assert np.isnan(batch["lost"]) and np.isnan(batch["zero"])


def test_max_requests_asks_the_highest_scores_first():
    world = make_world(4, 12, seed=3, windows={(0, b): [(0, 12)] for b in (1, 2, 3)})
    team, results = _run(world)
    a = team.agents[0]
    for p, s in {"r1": 0.7, "r2": 0.9, "r3": 0.8}.items():
        a.s.cur.scores[p] = s
        a.s.cur.memory_scores[p] = (s, -1)
    a.s.cur.request_rank, a.s.cur.requested, a.s.cur.skipped = None, {}, {}
    assert {p: a.wants_image(p) for p in ("r1", "r2", "r3")} == {"r1": False, "r2": True, "r3": True}
    assert a.s.cur.skipped == {"r1": "max-requests"}
    # the world's gate opens for all three peers of r0 at every step: two images a step
    asked = [sum(p.ego == "r0" and p.bytes_pair > 0 for p in res.pairs) for res in results]
    assert max(asked) == 2
