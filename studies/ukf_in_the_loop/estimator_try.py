"""What the feasibility scripts share: put another estimator in the closed loop's UKF's place, then run the control
test's first episodes from pretrained/pendulum_torque.ckpt (another SSM: ``"ssm": "<file.ckpt>"`` in the settings),
or, with ``"diagnose": "<file.md>"`` in the settings, score its estimates along the true-model controller's swing-ups
(studies/control_diagnosis's table)."""

from __future__ import annotations

import sys
from collections.abc import Callable
from pathlib import Path

import ssm_ms.control.module as M
from ssm_ms.cli import main

SSM = "pretrained/pendulum_torque.ckpt"


def try_estimator(
    prepare: Callable[[M.ClosedLoop], None], make: Callable[[M.ClosedLoop], object], settings: dict, name: str
) -> None:
    """``prepare(loop)`` once a learned model's loop is set up, ``make(loop)`` a fresh estimator for each batch; the
    results into ``settings["out"]`` (default ``runs/<name>``)."""
    attach = M.ClosedLoop.attach

    def attach_and_prepare(self, dm):
        attach(self, dm)
        if self.ssm is not None:  # the true model's controller has no estimator
            prepare(self)

    ssm = settings.get("ssm", SSM)
    M.ClosedLoop.attach = attach_and_prepare
    M.ClosedLoop.estimator = make
    if settings.get("diagnose"):
        sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "control_diagnosis"))
        from control_diagnosis import main as diagnose

        diagnose(["--ssm-checkpoint", ssm, "--out", settings["diagnose"]])
        return
    main(
        [
            "test",
            "--config",
            "configs/pendulum_torque_control.yaml",
            "--model.init_args.ssm_checkpoint",
            ssm,
            "--data.init_args.n_test",
            str(settings.get("episodes", 20)),
            "--model.init_args.results_dir",
            settings.get("out", f"runs/{name}"),
            "--model.init_args.figures_dir",
            settings.get("figures", "null"),
            "--trainer.logger.init_args.version",
            name,
            "--trainer.inference_mode",
            "false",  # an estimator may fit by gradients
            "--model.init_args.method_name",
            f"{name} {settings}",
        ]
    )
