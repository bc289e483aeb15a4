"""The VLM supervisor: `FailureAnalyzer` on the prefix grid of the keyframes so far (in process, one pass).

Q6 is decoded in template mode (the paper's correction-strategy table filled with the scene's names, among the
strategies of the category the model gave for Q5), so every correction it gives maps to primitives. The model
names a category (Q5), not a fine-grained type: the verdict's `failure_type` stays None and the diagnosis carries
the category. A failure whose grid frame lies at or before the last correction is taken as already handled.
The grid shows the supervisor's own `views` (supervise.yaml: the `cameras`), whatever else the policy sees.

When to intervene: P(failure) >= `threshold`; or the threshold an online bench calibrated (`alarm` + `alpha`); or,
with `monitor` + `alpha`, a robot-signal monitor that bench saved (sim_backends/supervision/monitor.py), as Sentinel
pairs a cheap detector with a VLM: while the policy runs, the monitor reads the robot's signals at every query and
the model is asked only once it sounds, for the diagnosis and the correction (its Q2 taken as a failure); after one
correction the monitor stands down for the episode. Once the policy stops, the model reviews the whole episode at
`threshold` (as without a monitor), but only in an episode the monitor flagged: the supervisor touches no episode
in which the calibrated alarm stayed quiet, so on successes exchangeable with its calibration ones (the scripted
policy's) it intervenes in at most alpha (the every-sample member reads live what the bench read; the per-frame one
reads the grid as laid out from the plan, close to the recorded one: sim_backends/supervision/monitor.py).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from labrobfail_vlm.bench.online_alarm import alpha_key
from labrobfail_vlm.config import ConfigError, is_number
from labrobfail_vlm.drawing import mismatches
from labrobfail_vlm.monitor import RobotMonitor
from sim_backends.policies.base import EpisodeContext
from sim_backends.source import FailureSource
from sim_backends.supervision.base import Supervisor, Verdict, live_grid, register_supervisor, view_indices
from sim_backends.supervision.monitor import LiveMonitor


def calibrated_threshold(alarm: str | None, alpha: float | None) -> float:
    """The threshold the online bench calibrated at `alpha` (its online.json, the model's row): the alarm fires
    when P(failure) is strictly above it, the analyzer when at or above, hence the next float up."""
    import json
    import math

    if alarm is None or alpha is None:
        raise ConfigError("vlm.alarm/vlm.alpha: give both (an online bench's online.json and one of its alphas)")
    try:
        bench = json.loads(Path(alarm).read_text())["rows"]
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise ConfigError(f"vlm.alarm: {alarm} is not an online bench's online.json ({type(e).__name__})") from None
    rows = bench.get("model") if isinstance(bench, dict) else None
    if not isinstance(rows, dict):  # a bench without model= (make online-power): its monitors are the robot's
        raise ConfigError(
            f"vlm.alarm: {alarm} has no model row (a bench run without model=); the supervisor runs the model's "
            "alarm only, not the robot-signal monitors"
        )
    row = rows.get(alpha_key(alpha))
    if row is None:
        raise ConfigError(f"vlm.alpha: {alpha!r} was not calibrated in {alarm} (it has {', '.join(rows)})")
    t = row.get("threshold")
    if t is None:
        raise ConfigError(
            f"vlm.alpha: too few calibration successes in {alarm} for alpha {alpha}: the alarm never fires"
        )
    if not is_number(t) or not 0.0 <= t <= 1.0:
        raise ConfigError(f"vlm.alarm: {alarm} gives alpha {alpha} the threshold {t!r}, not a P(failure) in [0, 1]")
    if t >= 1.0:  # no P(failure) is above 1: the bench's alarm never fires at this alpha, and neither would this
        raise ConfigError(f"vlm.alpha: the alarm calibrated in {alarm} at alpha {alpha} is 1.0: it never fires")
    return math.nextafter(float(t), math.inf)  # in (0, 1]: 1.0 from the float under it (an alarm at exactly P = 1)


@register_supervisor("vlm")
class VLMSupervisor(Supervisor):
    name = "vlm"

    def __init__(
        self,
        model: str | None = None,
        q6_mode: str = "template",
        device: str | None = None,
        analyzer: Any = None,
        threshold: float = 0.5,
        views: list[str] | None = None,
        alarm: str | None = None,
        alpha: float | None = None,
        check_drawing: bool = True,
        monitor: str | None = None,
        monitor_row: str | None = None,
    ):
        from labrobfail_vlm.analyzer import FailureAnalyzer, check_threshold
        from labrobfail_vlm.train.checkpoint import trained_drawing

        self.monitor: LiveMonitor | None = None
        if monitor is not None:  # the robot-signal alarm decides; the model diagnoses and corrects what it flagged
            if alarm is not None:
                raise ConfigError("vlm.monitor/vlm.alarm: one alarm decides when to intervene; give one of them")
            if alpha is None:
                raise ConfigError("vlm.monitor: give vlm.alpha too (one of the alphas its bench calibrated)")
            self.monitor = LiveMonitor(RobotMonitor.load(monitor, alpha, monitor_row))
        elif monitor_row is not None:
            raise ConfigError("vlm.monitor_row: names a row of vlm.monitor, which is not given")
        if alarm is not None or (alpha is not None and monitor is None):  # in (0, 1]: 1.0 from the float under 1
            threshold = calibrated_threshold(alarm, alpha)
        else:  # (with a monitor: the final review's, when the policy has stopped)
            try:
                threshold = check_threshold(threshold)
            except ValueError as e:
                raise ConfigError(f"vlm.{e}") from None
        if not isinstance(check_drawing, bool):
            raise ConfigError(f"vlm.check_drawing: true or false, got {check_drawing!r}")
        if analyzer is None:
            if not model or not Path(model).is_dir():
                raise ConfigError(f"vlm.model: no such model directory {model!r}")
            analyzer = FailureAnalyzer.from_pretrained(model, device=device, q6_mode=q6_mode)
        analyzer.threshold = threshold  # intervene when P(failure) >= threshold
        self.fa = analyzer
        self.trained_drawing = trained_drawing(model) if model and check_drawing else None
        self.views = None if views is None else [str(v) for v in views]

    def check_cameras(self, rendered: list[str]) -> None:
        view_indices(rendered, self.views)

    def check_drawing(self, options: dict[str, Any]) -> None:
        off = mismatches(self.trained_drawing, options)
        if off:
            was = ", ".join(f"{k}={str(self.trained_drawing[k]).lower()}" for k in off)  # type: ignore[index]
            now = ", ".join(f"{k}={str(not self.trained_drawing[k]).lower()}" for k in off)  # type: ignore[index]
            raise ConfigError(
                f"vlm.model: its training grids were drawn with {was}, this run's with {now} (give backend_kwargs "
                "the same, or vlm.check_drawing=false to supervise anyway)"
            )

    def reset(self, ctx: EpisodeContext) -> None:
        super().reset(ctx)
        self.view_idx = view_indices(ctx.camera_names, self.views)
        self.reported: tuple[dict[str, Any], Verdict] | None = None  # the monitor's alarm and the model's verdict
        self.stood_down = False

    def handled(self, src: FailureSource, acted: bool = True) -> None:
        # The monitor's bound is on an episode's first alarm: no calibration success was corrected halfway, and on
        # the development block (docs/EXPERIMENTS.md, 7 Dec night) acting on its later alarms did more harm than
        # good (pick +3 against +96: a second regrasp dropping what the first one saved). It stands down.
        # A correction refused before it moved anything leaves the failure to the final review (the development
        # block's variant that kept it handled lost place and pour failures the review would have mended).
        if self.monitor is None or acted:
            super().handled(src, acted)
        self.stood_down = True

    def query(self, src: FailureSource, final: bool = False) -> Verdict:
        if self.monitor is None:
            return self._ask(src, final)
        if final and self.stood_down:  # the policy stopped in an episode the monitor flagged: the model's review
            return self._ask(src, final)
        hit = None if self.stood_down else self.monitor.check(src, self.ctx.nominal)
        if hit is None:  # quiet: the model is not asked (Sentinel's cheap detector first), not even at the end
            return Verdict(False, diagnosis={"failure": False, "monitor": None})
        if self.reported is None or self.reported[0] != hit:  # an alarm the loop did not act on (its budget spent)
            self.reported = (hit, self._ask(src, final, hit))  # is diagnosed once, not at every later keyframe
        return self.reported[1]

    def _ask(self, src: FailureSource, final: bool, hit: dict[str, Any] | None = None) -> Verdict:
        """The model on the live grid; after the monitor's alarm (`hit`) its verdict is a failure whatever its
        P(failure) (the operating point 0 for this one ask), and Q3-Q6 say which and how to correct it."""
        g = live_grid(src, self.ctx.nominal, self.fa.grid, final, self.view_idx)
        operating_point = self.fa.threshold
        if hit is not None:
            self.fa.threshold = 0.0
        try:
            d = self.fa.analyze(g.image, task=self.ctx.instruction, frames=max(1, g.visible), objects=self.ctx.objects)
        finally:
            self.fa.threshold = operating_point
        kf = g.keyframes[d.failure_frame - 1] if d.failure and d.failure_frame and g.keyframes else None
        if hit is not None and (kf is None or kf <= self.handled_upto):  # the model's frame is one already dealt with
            kf = hit["keyframe"]
        new = d.failure and (kf is None or kf > self.handled_upto)
        return Verdict(
            bool(new),
            None,
            kf,
            d.correction if new else "",
            d.correction_strategy if new else None,
            list(d.primitives or []) if new else [],
            {k: v for k, v in d.__dict__.items() if k != "raw"} | {"raw": d.raw, "monitor": hit},
            g.image,
        )
