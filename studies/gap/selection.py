"""Choose the effects that explain the gap: each candidate fitted alone and judged, the
candidates ranked, and a combination selected greedily.

The single candidates are ranked by the held-out MAE they remove, significant ones only
(``Judged.explains``); where simpler candidates tie with the best, the simplest comes
first (``rank``). Forward selection then adds, one at a time, the effect that most
improves the held-out MAE of the combination fitted jointly, while the step's paired
improvement is significant (``forward``). The fits come from ``studies.gap.fit`` and the
judgements from ``studies.gap.judge``; here they are callables:

- ``fit_effects(names, start=None, free=None, max_iterations=MAX_ITERATIONS) -> Fit``
  (``Fitter.fit``);
- ``judge(fit, against=None, complete=True) -> Judged`` (``Judge.judge``).
"""

from __future__ import annotations

import numpy as np

from . import metrics
from .fit import Fit
from .judge import RANK_BY, Judged

#: A forward-selection step must also close at least this share of the original gap.
MIN_STEP_SHARE = 0.01
#: A reference model's candidate that closes the held-out gap to within this share of it
#: of the best one's ties with it for the first place (``rank``). A re-rendered
#: candidate's prediction carries the basis' Monte Carlo noise, and camera_gains' none:
#: on the physical benchmark the hidden absorption (98 per m, fitted 97.8), albedo (0.708,
#: fitted 0.707) and core leak were beaten by camera_gains (11 parameters) by 0.2 %, 1.7 %
#: and 0.7 % of the gap, each significant on the paired held-out taps (the absorption,
#: predicted at its hidden value, left a masked MAE of 0.0149 on six of the taps; the
#: fitted camera_gains, 0.0150 on the held-out six).
RANK_TIE_SHARE = 0.02
#: A pair drawn from this many of the best-ranked single candidates of a reference model
#: may take the first place from a single one with more parameters (``rank``).
PAIR_POOL = 4
#: L-BFGS-B iterations of the joint refit of a selected combination.
JOINT_ITERATIONS = 15
#: Forward selection tries at most this many remaining candidates per step (the best
#: single ones).
MAX_TRIALS = 3
#: At most this many effects in a selected combination.
MAX_COMBINATION = 4


def singles(effects: tuple[str, ...], fit_effects, judge, unjudged, model, progress=None,
            screen=None) -> dict[str, Judged]:
    """Each effect fitted alone and judged on the held-out samples, except the
    re-rendered candidates of a reference model beyond its ``judged_renders`` lowest
    training losses (``screened``): judging one renders every held-out tap (one
    re-weighted from the identity's photons renders nothing of its own: ``costly``).

    With ``screen`` (``fit_effects`` on the model's ``screen_taps`` of the fit's taps),
    where more costly candidates are left than ``judged_renders``, each is first fitted
    on those few taps, and only the best there (the lowest share of the training loss
    left) are fitted on every fit tap and judged; the rest keep their screen's fit,
    unjudged. The others are fitted first: their identity renders say which re-rendered
    candidates are costly (a grid point re-weighted or traced again).

    unjudged : ``Judge.unjudged``, the judgement of a fit left unjudged; model : the
    working model; progress : called with (done, total, what) after each step."""
    fits, out, steps, done = {}, {}, 2 * len(effects), [0]

    def step(what: str) -> None:
        done[0] += 1
        if progress is not None:
            progress(done[0], steps, what)

    keep = getattr(model, "judged_renders", None)
    rerendered = getattr(model, "rerendered", lambda name: False)
    deferred = []
    for name in [n for n in effects if not rerendered(n)] + [n for n in effects if rerendered(n)]:
        if screen is not None and keep is not None and rerendered(name) and model.costly(name):
            deferred.append(name)
            continue
        fits[name] = fit_effects((name,))
        step(name)
    screens, left = {}, {}
    if deferred and len(deferred) > keep:  # screened first; only the best there are fitted fully
        for name in deferred:
            screens[name] = screen((name,))
            screens[name].status["screen"] = {"taps": int(model.screen_taps), "train_loss": screens[name].train_loss,
                                              "train_loss_before": screens[name].train_loss_before}
            if progress is not None:
                progress(done[0], steps, f"{name}, screened on {model.screen_taps} taps")
        left = {n: f.train_loss / max(f.train_loss_before, 1e-30) for n, f in screens.items()}
    survivors = sorted(deferred, key=left.get)[:keep] if screens else deferred
    left_out = {}
    for name in deferred:
        if name in survivors:
            fits[name] = fit_effects((name,))
            if name in screens:
                fits[name].status["screen"] = screens[name].status["screen"]
        else:
            fits[name] = screens[name]
            left_out[name] = (f"not judged on the held-out samples: fitted on {model.screen_taps} of the fit's "
                              f"taps only, it left {left[name]:.1%} of their training loss, not among the "
                              f"{keep} lowest of the re-rendered candidates traced again "
                              f"({', '.join(survivors)}), which alone were fitted on every fit tap; judging "
                              f"one renders every held-out tap")
        step(name)
    left_out = left_out or screened(fits, model)
    for name in effects:
        # SSIM (most of a judgement's time) only for those that explain part of the gap
        out[name] = judge(fits[name], complete=None) if name not in left_out else unjudged(fits[name], left_out[name])
        step(f"{name}, judged on the held-out samples")
    return out


def screened(fits: dict[str, Fit], model) -> dict[str, str]:
    """{name: why} the fitted single effects left unjudged (``singles``)."""
    keep = getattr(model, "judged_renders", None)
    if keep is None:
        return {}
    costly = [n for n in fits if model.costly(n)]
    if len(costly) <= keep:
        return {}
    order = sorted(costly, key=lambda n: fits[n].train_loss)
    return {n: (f"not judged on the held-out samples: its training loss ({fits[n].train_loss:.4g} of "
                f"{fits[n].train_loss_before:.4g}) was not among the {keep} lowest of the re-rendered candidates "
                f"({', '.join(order[:keep])}), and judging one renders every held-out tap")
            for n in order[keep:]}


def size(effect) -> int:
    """A candidate's parameters (an ``effects.Effect``), the capture's exposure (fitted with
    every physical one) not counted."""
    return sum(p.name != "exposure" for p in effect.params)


def rank(singles: dict[str, Judged], before: dict, sizes: dict[str, int], ties_to_simplest: bool, fit_effects,
         judge, seed: int = 0) -> tuple[list[str], Judged | None]:
    """(the single effects that explain part of the gap, the pair ranked first or None).

    The effects that explain part of the gap (``Judged.explains``: significant and
    closing at least ``MIN_RANK_SHARE`` of it), best held-out MAE improvement first. A
    reference model's candidates are ranked by that too, except that the first is the
    one with the fewest parameters (``sizes``) among those the best does not beat
    significantly (paired held-out MAE) or beats by at most ``RANK_TIE_SHARE`` of the gap:
    its image-level models of the unit's camera (camera_gains, 11 parameters) mimic a
    physical colour or brightness change nearly as well and then would take the first
    place by noise alone (measured: hidden camera_response and led_spectra switches
    were fitted exactly, and ranked second to it). A fast model does the same when
    its candidates are fitted with the capture's exposure (``FastModel.ties_to_simplest``):
    its camera_response then beat a hidden absorption's path_attenuation by 1.7 % of the
    gap. A pair with fewer parameters than that first one may take the first two
    places (``_pair``).

    before : the held-out metrics of the simulator as it is (``Judge.before``)."""
    ranked = [n for n, j in sorted(singles.items(), key=lambda kv: -kv[1].gain) if j.explains]
    if not ties_to_simplest or len(ranked) < 2:
        return ranked, None
    best = singles[ranked[0]].after[RANK_BY[0]][RANK_BY[1]]
    margin = RANK_TIE_SHARE * float(np.mean(before[RANK_BY[0]][RANK_BY[1]]))

    def tied(judged: Judged) -> bool:
        other = judged.after[RANK_BY[0]][RANK_BY[1]]
        if float(np.mean(other)) - float(np.mean(best)) <= margin:
            return True
        return not metrics.improvement(other, best, RANK_BY[1], seed=seed)["significant"]

    first = min((n for n in ranked if tied(singles[n])), key=lambda n: (sizes[n], ranked.index(n)))
    first_pair = _pair(singles, ranked, first, tied, before, sizes, fit_effects, judge, seed)
    if first_pair is not None:
        first_pair.instead_of = first
        pair = sorted(first_pair.fit.effects, key=ranked.index)
        return pair + [n for n in ranked if n not in pair], first_pair
    return [first] + [n for n in ranked if n != first], None


def _pair(singles: dict[str, Judged], ranked: list[str], first: str, tied, before: dict, sizes: dict[str, int],
          fit_effects, judge, seed: int) -> Judged | None:
    """The pair that takes the first place from ``first``, if one does: drawn from the
    ``PAIR_POOL`` best-ranked candidates, with fewer parameters than ``first``, tied
    with the best single (``tied``, as ``rank``'s rule) and better than each of its two
    alone by what a selection step must close (significant, ``MIN_STEP_SHARE``).
    Among several, the fewest parameters, then the lowest held-out MAE.

    A hidden cause of two physical effects (LED peaks shifted and the camera's
    response off; the coating's albedo and the medium's absorption) is mimicked by the
    unit's flexible camera model (camera_gains, 11 parameters) better than by either
    effect alone, so ranking single candidates named the camera: the same parsimony
    as the tie rule, over pairs."""
    pool = ranked[:PAIR_POOL]
    gap = float(np.mean(before[RANK_BY[0]][RANK_BY[1]]))
    found = []
    for i, a in enumerate(pool):
        for b in pool[i + 1:]:
            if sizes[a] + sizes[b] >= sizes[first]:
                continue
            judged = judge(jointly(fit_effects, added(fit_effects, singles[a].fit, b, singles)), complete=False)
            after = judged.after[RANK_BY[0]][RANK_BY[1]]

            def adds_to(alone: Judged) -> bool:  # the pair against one of its two alone
                alone_after = alone.after[RANK_BY[0]][RANK_BY[1]]
                return _adds(metrics.improvement(alone_after, after, RANK_BY[1], seed=seed), gap)

            if tied(judged) and adds_to(singles[a]) and adds_to(singles[b]):
                found.append((sizes[a] + sizes[b], float(np.mean(after)), judged))
    if not found:
        return None
    return judge(min(found, key=lambda t: t[:2])[2].fit)


def added(fit_effects, fit: Fit, name: str, singles: dict[str, Judged]) -> Fit:
    """Effect ``name`` fitted on top of ``fit`` (held fixed), from its single fit."""
    return fit_effects(fit.effects + (name,), start={**fit.params, name: singles[name].fit.params[name]},
                       free=(name,))


def jointly(fit_effects, fit: Fit) -> Fit:
    """``fit``'s effects refitted together (``JOINT_ITERATIONS``), where that fits better."""
    joint = fit_effects(fit.effects, start=fit.params, max_iterations=JOINT_ITERATIONS)
    return joint if joint.train_loss < fit.train_loss else fit


def forward(singles: dict[str, Judged], ranked: list[str], first_pair: Judged | None, before: dict, fit_effects,
            judge, train_loss) -> list[Judged]:
    """Greedy forward selection, chosen on the training samples, stopped on the
    held-out ones.

    The first step is the best significant single effect (of ``ranked``, ``rank``'s
    order; the pair ranked first, ``first_pair``, is the second step). At each later step
    every remaining effect is screened by the training loss (``train_loss(params)``,
    ``Fitter.train_loss``) of the current combination plus that effect with its
    single-fit parameters; the ``MAX_TRIALS`` best are fitted on top of the combination
    (held fixed), the one with the lowest training loss is refitted jointly with it, and
    the step is kept if its paired held-out improvement over the current combination
    (full resolution) is significant and closes at least ``MIN_STEP_SHARE`` of the
    original gap (``before``); otherwise selection stops. Held-out samples only decide
    when to stop and measure every step.
    """
    steps: list[Judged] = []
    if not ranked:
        return steps
    current = singles[ranked[0]]
    current.added = ranked[0]
    steps.append(current)
    pair = first_pair
    if pair is not None and set(pair.fit.effects) == set(ranked[:2]):  # ranked first as a pair: its second step
        pair.added = ranked[1]
        steps.append(pair)
        current = pair
    candidates = [n for n in singles if n not in current.fit.effects]
    gap = float(np.mean(before[RANK_BY[0]][RANK_BY[1]]))
    while candidates and len(current.fit.effects) < MAX_COMBINATION:

        def screening(name: str, params=current.fit.params) -> float:
            return train_loss({**params, name: singles[name].fit.params[name]})

        order = sorted(candidates, key=screening)
        trials = [(name, added(fit_effects, current.fit, name, singles)) for name in order[:MAX_TRIALS]]
        name, fit = min(trials, key=lambda t: t[1].train_loss)
        fit = jointly(fit_effects, fit)
        step = judge(fit, against=current.after, complete=False)
        if not _adds(step.improvement[RANK_BY[0]][RANK_BY[1]], gap):
            break
        # Reported against the simulator as it is, with every metric.
        best = judge(fit)
        best.step_improvement = step.improvement
        best.added = name
        steps.append(best)
        current = best
        candidates.remove(name)
    return steps


def _adds(improvement: dict, gap: float) -> bool:
    """Whether a paired held-out improvement (``metrics.improvement``) is what a selection
    step must close: significant, and at least ``MIN_STEP_SHARE`` of the gap."""
    return improvement["significant"] and improvement["mean"] >= MIN_STEP_SHARE * gap
