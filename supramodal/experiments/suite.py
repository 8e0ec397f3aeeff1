"""The paper's figures as plans (see :mod:`.common`), by name: what ``supramodal experiment`` runs."""

from __future__ import annotations

from typing import Any

from supramodal.errors import InputError
from supramodal.experiments import fig1, fig3, fig4, fig5, fig6
from supramodal.experiments.common import BANKS, Plan
from supramodal.mlp import DEFAULT_EPOCHS
from supramodal.textures import TextureSet

FIGURES = ("fig1", "fig3", "fig4", "fig5", "fig6")
#: Random texture sets per bank that ``experiment all`` adds to Fig. 3 (none in quick mode).
ALL_SETS = 5
#: Experiments beyond the paper's figures that run as plans too (not part of ``all``).
EXTRA = ("calibration",)


def plans(figure: str, quick: bool = False, epochs: int = DEFAULT_EPOCHS, seed: int = 0, sets: int | None = None,
          bank: str | None = None, texture_set: TextureSet | None = None) -> dict[str, Plan]:
    """Plans of ``figure`` (one of :data:`FIGURES`, ``"all"`` or one of :data:`EXTRA`), keyed by figure name.

    Fig. 3 options: ``bank`` (default: both, or the bank of ``texture_set``), ``texture_set``
    (default: the reference set), ``sets``: for ``fig3``, N > 1 random sets *instead of* the
    reference set (as before); for ``all``, N random sets per bank *besides* the reference
    sets (default :data:`ALL_SETS`, 0 in quick mode); for ``calibration``, N >= 1 random sets per
    bank and N two-sense sets (:func:`supramodal.experiments.calibration.plan`).
    """
    if figure not in FIGURES + ("all",) + EXTRA:
        raise InputError(f"unknown figure {figure!r}; choose one of {', '.join(FIGURES + EXTRA)} or all")
    if sets is not None and sets < 0:
        raise InputError(f"--sets must be >= 0, got {sets}")
    if figure == "calibration":
        from supramodal.experiments import calibration

        if bank is not None or texture_set is not None:
            raise InputError("--bank and --textures apply to fig3, not to calibration (it measures both banks)")
        return {figure: calibration.plan(quick=quick, epochs=epochs, seed=seed, sets=sets)}
    common: dict[str, Any] = {"quick": quick, "epochs": epochs}
    if figure == "all":
        if bank is not None or texture_set is not None:
            raise InputError("--bank and --textures apply to fig3 alone, not to all")
        n_sets = (0 if quick else ALL_SETS) if sets is None else sets
        fig3_plan = fig3.plan(BANKS, reference=True, sets=n_sets, seed=seed, **common)
        return {"fig1": fig1.plan(**common), "fig3": fig3_plan, "fig4": fig4.plan(**common),
                "fig5": fig5.plan(**common), "fig6": fig6.plan(**common)}
    if figure != "fig3":
        if bank is not None or texture_set is not None or sets is not None:
            raise InputError("--bank, --textures and --sets apply to fig3 (and --sets to all)")
        return {figure: {"fig1": fig1, "fig4": fig4, "fig5": fig5, "fig6": fig6}[figure].plan(**common)}
    if texture_set is not None:
        if sets is not None and sets > 1:
            raise InputError("--sets draws random texture sets; it cannot be combined with --textures")
        if bank is not None and bank != texture_set.bank:
            raise InputError(f"texture set {texture_set.name!r} is for the {texture_set.bank} bank, not {bank}: "
                             f"pass --bank {texture_set.bank}")
        banks: tuple[str, ...] = (texture_set.bank,)
    else:
        banks = BANKS if bank is None else (bank,)
    random_sets = sets if sets is not None and sets > 1 else 0      # N > 1: random sets instead of the reference
    return {"fig3": fig3.plan(banks, texture_set=texture_set, reference=not random_sets, sets=random_sets,
                              seed=seed, **common)}
