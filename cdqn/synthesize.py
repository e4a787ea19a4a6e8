"""Design report without training (Hydra, the same config groups as :mod:`cdqn.train`)::

    python -m cdqn.synthesize env=cartpole controller=hinf_f out=designs/cartpole_hinf_f
    python -m cdqn.synthesize env=acrobot controller=hinf controller.synthesis.ntk_bounds=measured

Prints the report (box, weights, achieved γ, matrices or gains, certificate, time) and
writes into ``out``: ``controller.json`` (keys ``kind``, ``A``, ``B``, ``C``, ``D``,
``theta_bounds``, ``discount``, ``gamma``, ...), ``report.txt``, ``closed_loop_sv.csv``
(``omega, sigma_max, sigma_min``) and the plots ``weights_bode.png``, ``cover.png``,
``closed_loop_sv.png``, ``ntk_box.png``.  ``controller=h2`` reports the scheduled LQR over
the box.  Exit status 2 on a configuration or design error, with the reason.
"""

from __future__ import annotations

import json
import logging
import shutil
import sys
from pathlib import Path

import hydra
import numpy as np
from omegaconf import DictConfig

from cdqn.config import CONF_DIR, ConfigError, SynthesizeConfig, of_kind, register_configs
from cdqn.control.errors import DesignError

log = logging.getLogger("cdqn.synthesize")
register_configs()


def h2_report(conf: SynthesizeConfig, out: Path) -> str:
    """The gain-scheduled H2 as training runs it (:func:`cdqn.control.factory.make_controller`:
    LQR gains, gain map, learning target, certificate over the box), with its gains at the
    box's corners and nominal point."""
    from cdqn.control.design import box_from_config
    from cdqn.control.factory import make_controller
    from cdqn.control.h2 import scheduled_gains
    from cdqn.control.runtime import ScheduledLQR

    setup = make_controller(conf.controller, conf.weights, conf.train.discount, conf.train.lr)
    record = dict(setup.design)
    box = box_from_config(conf.weights.theta_bounds)
    ctrl = setup.controller
    assert isinstance(ctrl, ScheduledLQR)  # controller=h2
    pts = np.vstack([box.corners(), [box.nominal]])
    gains = scheduled_gains(pts, conf.train.discount, ctrl.w_x, ctrl.w_c, ctrl.research_map,
                            ctrl.target)  # fmt: skip
    record["gains_at"] = {
        f"({t1:.4g}, {t2:.4g})": g.tolist() for (t1, t2), g in zip(pts, gains, strict=True)
    }
    out.mkdir(parents=True, exist_ok=True)
    (out / "controller.json").write_text(json.dumps(record, indent=2))
    lines = [
        f"controller: h2 (gain-scheduled LQR, W_x = {record['w_x']}, W_c = {record['w_c']:g}, "
        f"gain map {record['gain_map']})"
    ]
    lines += [
        f"  (k1, k2, k3) at {k}: {[round(v, 6) for v in g]}" for k, g in record["gains_at"].items()
    ]
    lt = record.get("learning_target")
    if lt:
        lines.append(
            f"learning target kept over the box: γ_eff ∈ [{lt['gamma_eff'][0]:.4g}, "
            f"{lt['gamma_eff'][1]:.4g}], 1 + k1 ∈ [{lt['step_scale'][0]:.4g}, "
            f"{lt['step_scale'][1]:.4g}] (target {lt['target']}); largest α(1 + k1)Θ1 = "
            f"{lt['max_step_gain']:.4g}"
        )
        c = record["certificate"]
        lines.append(
            f"certificate (frozen at each point): PASSED on {c['n_points']} points; worst pole "
            f"Re λ = {c['worst_pole']:.6g}; Δt = α loop max |λ| = {c['worst_discrete_modulus']:.9f}"
        )
    return "\n".join(lines)


def synthesize(cfg: DictConfig) -> str:
    """Design, write the artefacts into ``cfg.out``, return the report."""
    from cdqn.envs import adopt

    adopted = adopt(cfg)  # env.id=<id>: that environment's cap, threshold and NTK box
    if adopted.change is not None:
        log.info("%s", adopted.change)
    conf = of_kind(adopted.conf, SynthesizeConfig)
    out = Path(conf.out)
    if conf.controller.name == "h2":
        return h2_report(conf, out)
    if conf.controller.name not in ("hinf", "hinf_f"):
        raise ConfigError(
            f"controller={conf.controller.name!r}: synthesize designs hinf, hinf_f or h2"
        )
    from cdqn.control.design import (
        cache_root,
        design_inputs,
        with_box_source,
        with_record_source,
    )
    from cdqn.control.synthesis import load_or_design

    box = None
    if conf.controller.synthesis.ntk_bounds == "measured":
        import torch

        from cdqn.envs import env_sizes, make_env
        from cdqn.network import NetworkSpec, QNetwork
        from cdqn.ntk_bounds import measured_box

        env = make_env(conf.env)
        n_obs, n_actions = env_sizes(env)
        env.close()
        torch.manual_seed(conf.seed)
        net = QNetwork(NetworkSpec(n_obs, n_actions, conf.network.width, conf.network.dtype))
        conf.controller.design = "synthesize"
        box = measured_box(conf, net)
    inputs = design_inputs(conf.controller, conf.weights, conf.train.discount, conf.train.lr, box)
    syn = conf.controller.synthesis
    record, folder, design = load_or_design(inputs, cache_root(syn) if syn.cache else None)
    out.mkdir(parents=True, exist_ok=True)
    if folder.resolve() != out.resolve():
        for item in folder.iterdir():
            if item.is_file():
                shutil.copy2(item, out / item.name)
        record = with_record_source(record, inputs.box.source)  # this box's, not the cache's
        (out / "controller.json").write_text(json.dumps(record, indent=2))
    text = with_box_source((out / "report.txt").read_text().rstrip(), inputs.box.source)
    if design is None:
        text += f"\n(from cache: {folder})"
    elif not syn.cache:
        shutil.rmtree(folder, ignore_errors=True)
    return text


@hydra.main(version_base="1.3", config_path=str(CONF_DIR), config_name="synthesize")
def main(cfg: DictConfig) -> None:
    try:
        print(synthesize(cfg))
        print(f"artefacts in {Path(cfg.out).resolve()}")
    except (ConfigError, DesignError) as err:
        print(f"error: {err}", file=sys.stderr)  # once, on stderr
        sys.exit(2)


if __name__ == "__main__":
    main()
