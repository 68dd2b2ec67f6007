"""The learn run's report: on the held-out objects, how often the first grasp a user gets holds, with the hand's
learned parts against the geometric sampler ranked by E, side by side, and which parts to install.

Orders compared (each over the valid candidates of each held-out object; an object without one fails):
    geometric + E           what the hand gets with no learned part (the baseline)
    geometric + predictor   the predictor alone installed
    cvae + E                the CVAE alone installed
    cvae + predictor        both installed
"Holds" is the robust verdict of lift-shake and six-dir in the same trials (`physics.robust`, 7 of 8 at the
defaults). The parts installed are those of the best order when it beats the baseline; ties keep fewer parts.
Beside them, each sampler's bound: the objects where some valid candidate holds, what a perfect ranker would get.
"""

import json
from pathlib import Path

import numpy as np

from ffcgs_jax.core import files
from ffcgs_jax.evaluation import rank_metrics
from ffcgs_jax.learn.config import LearnConfig
from ffcgs_jax.learning.weights import load_evaluator
from ffcgs_jax.training import evaluator_data, evaluator_train

ORDERS = (("geometric", "E", ()), ("geometric", "predictor", ("evaluator",)), ("cvae", "E", ("cvae",)),
          ("cvae", "predictor", ("cvae", "evaluator")))


def first_holds(data: evaluator_data.LabelData, score: np.ndarray) -> dict[str, bool]:
    """Per object of `data`: does its best-scored valid candidate hold both protocols?"""
    held = rank_metrics.first_valid_holds(score, evaluator_data.positives(data)[:, -1], data.objects, data.valid)
    return dict(zip(map(str, np.unique(data.objects)), held.tolist(), strict=True))


def scores(hand, files_: list[str], weights: str | None) -> dict[str, dict[str, bool]]:
    """{"E", "predictor", "bound": per object} over the label files `files_` (objects are named per file);
    "bound": some valid candidate holds."""
    out: dict[str, dict[str, bool]] = {"E": {}, "predictor": {}, "bound": {}}
    net = load_evaluator(weights, hand)[0] if weights else None
    for f in files_:
        data = evaluator_data.load(f, hand, progress=False, held_out=True)
        order = {"E": -data.E,
                 "bound": evaluator_data.positives(data)[:, -1].astype(float)}  # holders first: the best ranker
        if net is not None:
            order["predictor"] = evaluator_train.predict_rows(net, data.x)[:, -1]
        for kind, score in order.items():
            out[kind].update({f"{Path(f).stem}/{k}": v for k, v in first_holds(data, score).items()})
    return out


def write(cfg: LearnConfig, hand, work: Path, stages: dict) -> dict:
    predictor = stages["predictor"]["weights"]
    geo = scores(hand, stages["held_geometric"]["files"], predictor)
    cvae_files = stages["held_learned"]["files"]
    learned = scores(hand, cvae_files, predictor) if cvae_files else None
    n = len(geo["E"])
    rows = []
    for sampler, order, parts in ORDERS:
        if sampler == "cvae" and learned is None:  # no CVAE was learned: nothing of it to compare
            continue
        got = (geo if sampler == "geometric" else learned)[order]
        rows.append({"sampler": sampler, "order": order, "parts": list(parts), "first_holds": sum(got.values()),
                     "objects": n})
    install, best = choose(rows)
    base = rows[0]["first_holds"]
    bound = {"geometric": sum(geo["bound"].values())} | ({"cvae": sum(learned["bound"].values())} if learned else {})
    weights = {"cvae": stages["cvae"]["weights"], "evaluator": predictor}
    trained = stages["plan"]["objects"] + stages["plan"].get("folder_objects", 0)  # a folder planned before: 0
    rep = {"hand": hand.spec.name, "held_out_objects": n, "rows": rows, "bound": bound, "install": install,
           "weights": weights, "train_objects": trained, "per_object": cfg.per_object,
           "cvae_epochs": stages["cvae"].get("epochs"), "predictor_epochs": stages["predictor"]["epochs"]}
    files.write_text(work / "report.json", json.dumps(rep, indent=1))
    files.write_text(work / "report.md", markdown(rep))
    picture(rep, work / "report.png")
    verdict = (f"learned parts ({' + '.join(install)}) beat geometric + E" if install
               else "the geometric sampler ranked by E stays: the learned parts did not beat it")
    return rep | {"say": f"report in {work / 'report.md'}: {verdict} "
                         f"({best['first_holds']} against {base} of {n} held-out first grasps hold)"}


def choose(rows: list[dict]) -> tuple[list[str], dict]:
    """(the parts to install, the best row): the best order's parts when it beats the baseline (the first row);
    among equals the fewest parts, since a part that adds nothing is one more thing to go stale."""
    best = max(rows, key=lambda r: (r["first_holds"], -len(r["parts"])))
    return (list(best["parts"]) if best["first_holds"] > rows[0]["first_holds"] else []), best


def markdown(rep: dict) -> str:
    lines = [f"# Learned parts of hand {rep['hand']}", "",
             f"Training: {rep['train_objects']} objects, {rep['per_object']} labelled candidates each (robust "
             f"verdicts); CVAE {rep['cvae_epochs'] or 'not trained, no'} epochs, predictor "
             f"{rep['predictor_epochs']} epochs.", "",
             f"Held out: {rep['held_out_objects']} objects never trained on. First grasp holds: the first valid "
             "candidate in the order holds lift-shake and six-dir in the same robust trials.", "",
             "| sampler | order | first grasp holds |", "|---|---|---|"]
    for r in rep["rows"]:
        lines.append(f"| {r['sampler']} | {r['order']} | {r['first_holds']} / {r['objects']} "
                     f"({r['first_holds'] / max(r['objects'], 1):.0%}) |")
    bound = rep.get("bound", {})
    if bound:
        lines += ["", "A perfect ranker of the same candidates (some valid candidate holds): " + ", ".join(
            f"{k} {v} / {rep['held_out_objects']}" for k, v in bound.items()) + "."]
    lines += ["", f"Installed: {', '.join(rep['install'])}." if rep["install"] else
              "Installed: nothing. The learned parts did not beat the geometric sampler ranked by E on the held-out "
              "objects, so the hand keeps it."]
    return "\n".join(lines) + "\n"


def picture(rep: dict, png: Path) -> Path | None:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    fig, ax = plt.subplots(figsize=(5, 3))
    names = [f"{r['sampler']}\n+ {r['order']}" for r in rep["rows"]]
    share = [r["first_holds"] / max(r["objects"], 1) for r in rep["rows"]]
    ax.bar(names, share, color=["gray"] + ["tab:blue"] * (len(names) - 1))
    for i, r in enumerate(rep["rows"]):  # the sampler's bound: what a perfect ranker of its candidates gets
        if r["sampler"] in rep.get("bound", {}):
            ax.hlines(rep["bound"][r["sampler"]] / max(r["objects"], 1), i - 0.4, i + 0.4, colors="black",
                      linestyles="dashed", label="perfect ranker" if i == 0 else None)
    if rep.get("bound"):
        ax.legend(loc="upper right", fontsize=8)
    ax.set(ylim=(0, 1), ylabel="first grasp holds", title=f"{rep['hand']}: {rep['held_out_objects']} held-out objects")
    fig.tight_layout()
    with files.atomic_path(png) as tmp:
        fig.savefig(tmp, dpi=90)
    plt.close(fig)
    return png
