"""What building a controller yields: the runtime controller and the record of its design."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cdqn.control.box import Box
from cdqn.control.runtime import RuntimeController


@dataclass
class ControllerSetup:
    """The runtime controller and the record of where its design came from."""

    controller: RuntimeController
    source: str
    """``paper`` (research-code values), ``synthesized`` or ``scheduled`` (per-step LQR)."""
    design: dict[str, Any] = field(default_factory=dict)
    """Design record, logged as ``design/controller.json`` (gains or matrices, bounds,
    certificate)."""
    artifacts: Path | None = None
    """A folder of further design artefacts (plots, tables), logged under ``design/``."""

    def box(self) -> Box | None:
        """The NTK box the design covers, ``((Θ1 lo, Θ1 hi), (Θ2/Θ1 lo, hi))``, from the design
        record's ``theta_bounds``; ``None`` for a design without one (the research code's
        values, no controller, Double DQN)."""
        tb = self.design.get("theta_bounds")
        if not tb:
            return None
        return (float(tb["theta1"][0]), float(tb["theta1"][1])), (
            float(tb["ratio"][0]),
            float(tb["ratio"][1]),
        )

    def tags(self) -> dict[str, str]:
        """What the design keeps, as run tags: ``design_gamma_eff`` and ``design_step_scale``
        (γ_eff and 1 + k1; DC values for ``hinf``; ``lo..hi`` over the box for ``h2``),
        ``design_max_step_gain`` (largest α(1 + k1)Θ1 over the box) and
        ``design_worst_pole`` (certificate); empty for designs without a learning target."""
        lt = self.design.get("learning_target")
        if not lt:
            return {}

        def fmt(v: Any) -> str:
            if isinstance(v, list | tuple):
                return f"{v[0]:.6g}..{v[1]:.6g}"
            return f"{v:.6g}"

        cert = self.design.get("certificate", {})
        out = {
            "design_gamma_eff": fmt(lt["gamma_eff"]),
            "design_step_scale": fmt(lt["step_scale"]),
            "design_max_step_gain": fmt(lt["max_step_gain"]),
        }
        if "worst_pole" in cert:
            out["design_worst_pole"] = fmt(cert["worst_pole"])
        return out
