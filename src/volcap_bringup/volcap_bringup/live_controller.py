"""live_controller: keeps a live graph real time by choosing which frame sets it processes.

    ros2 run volcap_bringup live_controller --ros-args -p cameras:="[cam0, cam1]"

Watches the first and the last camera's ``color/camera_info`` and ``depth/camera_info``
(relative names, so a launch remaps them onto a driver's; the capture stamps are all it reads) and the stages' reports
on ``/volcap/diagnostics``. Once per ``control_period_s`` it publishes, latched on
``/volcap/admission``, the rule every stage applies to capture stamps (``volcap_core.admission``):
one frame set in ``every``, the same sets in every camera's depth filter and colour corrector and
in the fusion. ``every`` rises when a stage drops admitted frames, a set is fused short of
cameras or the latency exceeds ``latency_budget_ms``, and falls again while the host's
CPU has room. It reports the live figures (input rate, meshes/s, share fused from every camera,
latency p50/p95, drops per stage, each stage's CPU time per delivered mesh and the compute bound:
the meshes/s this host's cores would sustain doing only that work) on ``/volcap/diagnostics``
and to ``on_summary``.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import psutil
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo
from std_msgs.msg import String

from volcap_core import qos, topics
from volcap_core.admission import AdmissionController
from volcap_core.conversions import stamp_to_ns
from volcap_core.ros import Diagnostics, declare_config, node_main
from volcap_core.settings import setting

STAGES = ('camera_pipeline', 'depth_filter', 'color_corrector', 'tsdf_fusion')


@dataclass
class LiveControllerConfig:
    cameras: tuple[str, ...] = setting(tuple(topics.camera_names(8)), 'camera namespaces of the rig',
                                       read_only=True)
    every: int = setting(0, 'admit one frame set in this many (0: chosen from the measured load)', 0, 1000)
    max_every: int = setting(60, 'the automatic choice never admits fewer than one set in this many', 1, 1000)
    latency_budget_ms: float = setting(1000.0, 'capture-to-mesh latency (p95) above which fewer sets are admitted',
                                       10.0, 60_000.0)
    headroom: float = setting(0.85, 'admit more sets only while the host CPU use at the higher rate stays under '
                              'this fraction', 0.1, 1.0)
    control_period_s: float = setting(1.0, 'how often the load is measured and the rule revised (s)', 0.1, 60.0,
                                      read_only=True)


def stage_of(status_name: str) -> str | None:
    """The stage of a ``/volcap/diagnostics`` status name (``depth_filter: depth filter cam0``)."""
    node = status_name.split(':', 1)[0].strip()
    return node if node in STAGES else None


def _number(text: str) -> float | None:
    try:
        return float(text)
    except ValueError:
        return None


class LiveController(Node):
    def __init__(self, on_summary=None, **node_options):
        """``on_summary(dict)`` receives the figures once per control period (``volcap live`` prints
        them); ``node_options`` let a composed process host it."""
        super().__init__('live_controller', **node_options)
        self.cfg = declare_config(self, LiveControllerConfig, self._on_config)
        self.on_summary = on_summary
        self.diagnostics = Diagnostics(self, 'live graph')
        self.controller = AdmissionController(min_every=max(1, self.cfg.every), max_every=self._max_every())
        self.pub = self.create_publisher(String, '/' + topics.ADMISSION, qos.LATCHED)
        self.pub.publish(String(data=self.controller.rule.to_text()))
        self.reports: dict[str, dict[str, float]] = {}      # status name -> numeric values
        self.create_subscription(DiagnosticArray, '/' + topics.DIAGNOSTICS, self._on_diagnostics, qos.EVENTS)
        self.input_stamps = 0
        # Two cameras' colour and depth stamps place the grid (a synchronised rig's cameras agree
        # within a millisecond or two; volcap monitor watches that); all sixteen streams would cost
        # this node a fifth of a core in rclpy's executor for no better grid.
        for cam in self.cfg.cameras[:1] + self.cfg.cameras[-1:] if len(self.cfg.cameras) > 1 else self.cfg.cameras:
            for stream, topic in (('color', topics.COLOR_INFO), ('depth', topics.DEPTH_INFO)):
                self.create_subscription(CameraInfo, topics.camera_topic(cam, topic),
                                         lambda m, key=(cam, stream): self._on_stamp(key, m), qos.SENSOR)
        self._previous: dict[str, dict[str, float]] = {}
        self._previous_t = time.monotonic()
        self._first_key = (self.cfg.cameras[0], 'color')
        psutil.cpu_percent()       # starts the host CPU measurement
        self.summary: dict = {}
        self.create_timer(self.cfg.control_period_s, self._step)

    def _max_every(self) -> int:
        return self.cfg.every if self.cfg.every else self.cfg.max_every

    def _on_config(self, cfg: LiveControllerConfig) -> None:
        self.cfg = cfg
        c = self.controller
        c.min_every, c.max_every, c.headroom = max(1, cfg.every), self._max_every(), cfg.headroom

    def _on_stamp(self, key, msg: CameraInfo) -> None:
        self.controller.observe(key, stamp_to_ns(msg.header.stamp))
        self.input_stamps += key == self._first_key

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            if stage_of(status.name):
                # Warnings carry no counters: keep the last ones reported.
                self.reports.setdefault(status.name, {}).update(
                    {kv.key: v for kv in status.values if (v := _number(kv.value)) is not None})

    def _step(self) -> None:
        now = time.monotonic()
        dt, self._previous_t = now - self._previous_t, now
        summary = self._summarise(dt)
        trouble = bool(summary['trouble'])
        rule = self.controller.step(now, trouble, summary['cpu_busy'])
        if rule is not None:
            self.pub.publish(String(data=rule.to_text()))
        summary['admit_every'] = self.controller.rule.every
        self.summary = summary
        level = 'warn' if trouble else 'ok'
        self.diagnostics.report(level, self.line(summary), **{k: v for k, v in summary.items()
                                                               if not isinstance(v, (dict, list))})
        if self.on_summary is not None:
            self.on_summary(summary)

    def _delta(self, name: str, key: str) -> float:
        return self.reports.get(name, {}).get(key, 0.0) - self._previous.get(name, {}).get(key, 0.0)

    def _summarise(self, dt: float) -> dict:
        """This period's figures, from the stages' counters (their change since the last period)."""
        # the stages this graph runs (a camera_pipeline per camera, or a filter and a corrector)
        stages = [s for s in STAGES if any(stage_of(n) == s for n in self.reports)]
        drops = {s: {'dropped': 0.0, 'missed': 0.0, 'not_admitted': 0.0} for s in stages}
        work_s = dict.fromkeys(stages, 0.0)
        fusion = {}
        for name, values in self.reports.items():
            stage = stage_of(name)
            for key in drops[stage]:
                drops[stage][key] += max(0.0, self._delta(name, key))
            work_s[stage] += max(0.0, self._delta(name, 'work_s'))
            if stage == 'tsdf_fusion':
                fusion = {k: self._delta(name, k) for k in ('fused', 'fused_complete', 'incomplete')}
                fusion.update({k: values.get(k) for k in ('latency_ms_p50', 'latency_ms_p95')})
        self._previous = {n: dict(v) for n, v in self.reports.items()}
        fused = max(0.0, fusion.get('fused', 0.0))
        p95 = fusion.get('latency_ms_p95')
        # A stage's own drops are trouble; frames it missed are not by themselves (a camera or the
        # player that dropped a set makes every stage miss it, and more admission would not help):
        # a stage that lost frames to its queue shows downstream as a set fused incomplete.
        trouble = [f'{s} dropped' for s, d in drops.items() if d['dropped'] > 0]
        if fusion.get('incomplete', 0) > 0:
            trouble.append('tsdf_fusion incomplete sets')
        if p95 is not None and p95 > self.cfg.latency_budget_ms:
            trouble.append('latency over budget')
        input_fps, self.input_stamps = self.input_stamps / dt, 0
        # The stages' own CPU time per delivered mesh; the compute bound is the meshes/s this host's
        # cores would sustain doing nothing else.
        work_ms = {s: round(1000 * w / fused, 1) for s, w in work_s.items()} if fused else None
        bound = round(psutil.cpu_count() * 1000 / sum(work_ms.values()), 2) if work_ms and sum(work_ms.values()) \
            else None
        return {'work_ms_per_set': work_ms, 'compute_bound': bound, 'input_fps': round(input_fps, 2), 'meshes_per_s': round(fused / dt, 2),
                'complete_share': round(fusion.get('fused_complete', 0.0) / fused, 3) if fused else None,
                'latency_ms_p50': fusion.get('latency_ms_p50'), 'latency_ms_p95': p95,
                'cpu_busy': round(psutil.cpu_percent() / 100.0, 3),
                'drops_per_s': {s: {k: round(v / dt, 2) for k, v in d.items()} for s, d in drops.items()},
                'trouble': trouble, 'stages_reporting': {s: sum(stage_of(n) == s for n in self.reports)
                                                         for s in STAGES}}

    @staticmethod
    def line(s: dict) -> str:
        """The summary as one status line."""
        def ms(v):
            return '-' if v is None else f'{v:.0f}'
        d = s['drops_per_s']
        complete = '-' if s['complete_share'] is None else f'{100 * s["complete_share"]:.0f} %'
        return (f'in {s["input_fps"]:.1f} sets/s, admit 1/{s.get("admit_every", 1)}, out {s["meshes_per_s"]:.2f} '
                f'meshes/s ({complete} from all cameras), latency p50 {ms(s["latency_ms_p50"])} ms '
                f'p95 {ms(s["latency_ms_p95"])} ms, cpu {100 * s["cpu_busy"]:.0f} %'
                + (f', bound {s["compute_bound"]:.1f} meshes/s' if s['compute_bound'] else '') + '; drops/s: '
                + ', '.join(f'{stage} {v["dropped"]:.1f}+{v["missed"]:.1f} missed' for stage, v in d.items())
                + (f'; trouble: {", ".join(s["trouble"])}' if s['trouble'] else ''))


def main(args=None):
    node_main(LiveController, args)


if __name__ == '__main__':
    main()
