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
from omegaconf import DictConfig, OmegaConf

from cdqn.config import ConfigError, SynthesizeConfig, register_configs, validate
from cdqn.control.errors import DesignError

log = logging.getLogger("cdqn.synthesize")
register_configs()


def h2_report(conf: SynthesizeConfig, out: Path) -> str:
    """The scheduled LQR over the box on ``controller.synthesis.plant``: gains at corners and
    nominal, and its certificate (each point closed with its own gains, poles of the minimal
    part of the loop)."""
    from cdqn.control.certificate import ControllerMatrices, max_real_poles  # noqa: PLC0415
    from cdqn.control.design import box_from_config  # noqa: PLC0415
    from cdqn.control.h2 import h2_gains_plant  # noqa: PLC0415
    from cdqn.control.plant import check_plant  # noqa: PLC0415

    plant = check_plant(conf.controller.synthesis.plant)
    box = box_from_config(conf.weights.theta_bounds)
    w_x, w_c = np.asarray(conf.weights.h2.w_x, float), float(conf.weights.h2.w_c)
    discount = conf.train.discount
    pts = np.vstack([box.grid(*conf.controller.synthesis.grid), box.corners()])
    worst = -np.inf
    for t1, t2 in pts:
        K = ControllerMatrices.static(*h2_gains_plant(t1, t2, discount, w_x, w_c, plant))
        worst = max(worst, float(max_real_poles(np.array([[t1, t2]]), discount, K, plant)[0]))
    rows = {
        f"({t1:.4g}, {t2:.4g})": list(h2_gains_plant(t1, t2, discount, w_x, w_c, plant))
        for t1, t2 in np.vstack([box.corners(), [box.nominal]])
    }
    record = {
        "kind": "h2",
        "A": [],
        "B": [],
        "C": [],
        "D": [],
        "theta_bounds": {"theta1": list(box.theta1), "ratio": list(box.ratio)},
        "discount": conf.train.discount,
        "gamma": None,
        "plant": plant,
        "w_x": w_x.tolist(),
        "w_c": w_c,
        "gains_at": rows,
        "worst_pole": worst,
    }
    out.mkdir(parents=True, exist_ok=True)
    (out / "controller.json").write_text(json.dumps(record, indent=2))
    lines = [
        f"controller: h2 (gain-scheduled LQR, W_x = {w_x.tolist()}, W_c = {w_c:g}), "
        f"learning plant: {plant}"
    ]
    lines += [f"  (k1, k2, k3) at {k}: {[round(v, 6) for v in g]}" for k, g in rows.items()]
    lines.append(f"worst closed-loop pole over the box (own gains): Re λ = {worst:.6g}")
    return "\n".join(lines)


def synthesize(cfg: DictConfig) -> str:
    """Design, write the artefacts into ``cfg.out``, return the report."""
    from cdqn.envs import adopt_env_id  # noqa: PLC0415

    if (adopted := adopt_env_id(cfg)) is not None:  # env.id=<id>: that environment's box
        log.info("%s", adopted)
    conf: SynthesizeConfig = OmegaConf.to_object(cfg)  # type: ignore[assignment]
    validate(conf)
    out = Path(conf.out)
    if conf.controller.name == "h2":
        return h2_report(conf, out)
    if conf.controller.name not in ("hinf", "hinf_f"):
        raise ConfigError(
            f"controller={conf.controller.name!r}: synthesize designs hinf, hinf_f or h2"
        )
    from cdqn.control.design import (  # noqa: PLC0415
        cache_root,
        design_inputs,
        load_or_design,
    )

    box = None
    if conf.controller.synthesis.ntk_bounds == "measured":
        import torch  # noqa: PLC0415

        from cdqn.envs import env_sizes, make_env  # noqa: PLC0415
        from cdqn.network import NetworkSpec, QNetwork  # noqa: PLC0415
        from cdqn.ntk_bounds import measured_box  # noqa: PLC0415

        env = make_env(conf.env)
        n_obs, n_actions = env_sizes(env)
        env.close()
        torch.manual_seed(conf.seed)
        net = QNetwork(NetworkSpec(n_obs, n_actions, conf.network.width, conf.network.dtype))
        conf.controller.design = "synthesize"
        box = measured_box(conf, net)
    inputs = design_inputs(conf.controller, conf.weights, conf.train.discount, conf.train.lr, box)
    syn = conf.controller.synthesis
    _, folder, design = load_or_design(inputs, cache_root(syn) if syn.cache else None)
    out.mkdir(parents=True, exist_ok=True)
    if folder.resolve() != out.resolve():
        for item in folder.iterdir():
            if item.is_file():
                shutil.copy2(item, out / item.name)
    text = (out / "report.txt").read_text().rstrip()
    if design is None:
        text += f"\n(from cache: {folder})"
    elif not syn.cache:
        shutil.rmtree(folder, ignore_errors=True)
    return text


@hydra.main(version_base="1.3", config_path="../conf", config_name="synthesize")
def main(cfg: DictConfig) -> None:
    try:
        print(synthesize(cfg))
        print(f"artefacts in {Path(cfg.out).resolve()}")
    except (ConfigError, DesignError) as err:
        print(f"error: {err}", file=sys.stderr)  # once, on stderr
        sys.exit(2)


if __name__ == "__main__":
    main()
