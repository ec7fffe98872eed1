"""The outcome of the closed loop (`bfpsf.diagnosis.loop.diagnose`): `DiagnosisResult`."""

from dataclasses import dataclass, field

from ..outputs import json_safe

__all__ = ["DiagnosisResult"]


@dataclass(frozen=True)
class DiagnosisResult:
    """Outcome of the closed loop.

    Attributes
    ----------
    residual_before, residual_after : dict
        Residual summaries of the base model (the prediction as it stands: only the local
        nuisances fitted) and of the final model (effects and global nuisances fitted).
    candidates : list of dict
        One entry per candidate and round: ``round``, ``name``, ``statistic`` (Delta chi2,
        positive = better fit; None if not testable), ``delta_bic`` (None if not testable),
        ``k``, ``parameters`` and ``errors`` of the joint fit, ``testable``, ``allowed``
        (False: the fit is outside the effect's physical bounds, so it cannot be selected).
    selected : list of str
        Names of the added effects, in order (``name@physical``: fixed at its physical value).
    parameters : dict
        Final fitted parameters of each selected effect: name -> {value, error, physical}.
    threshold : float
    curves : dict
        Arrays for the plots: ``peak_e``, ``sigma_x``, ``sigma_y``, errors, ``base_x``,
        ``base_y`` (base model with fitted intercepts), ``final_x``, ``final_y``, ``group``.
    nuisance : dict
        Fitted global nuisances: ``calibration_scale`` and ``calibration_split`` {value,
        error, prior, signature, contradicted_by} when the size prediction carries the flats'
        errors of the BF amplitude and of its X / Y split (``meta['scale_err']``,
        ``meta['split_err']``, `bfpsf.diagnosis.problem.global_priors`).
    residual_before_heldout, residual_after_heldout : dict or None
        With a held-out split: the residual summaries (same keys as ``residual_after``) on the
        held-out data, the effects and global nuisances fixed at their in-sample values and
        only the local nuisances (intercepts, linearity zero point and slope, PTC noise and
        gain) refitted.
    residual_physical_heldout : dict or None
        ``residual_physical`` on the held-out data.
    confirmed : dict
        Selected effect -> True when adding it lowered the held-out chi2 (in the order
        selected), False ("not confirmed") otherwise. Empty without a split.
    holdout : dict or None
        How the data were split (``fraction``, ``sizes_split_by``, row counts).
    unexplained : list of dict
        Significant residuals no confirmed effect explains: {observable, axis, parity,
        flux_dependence, significance} (`describe_unexplained`).
    rejected : dict
        Candidates that passed the information criterion but not the signature test
        (`bfpsf.diagnosis.signature`): name -> {``round``, ``delta_bic``, ``contradicted_by``
        (the dimension with the smallest p-value), ``p_value``, ``signature`` (every
        dimension's test)}; or, for a fit outside its effect's physical ``bounds``,
        ``contradicted_by`` 'bounds' with its ``values``. The round it was rejected in; it is not tested again in later
        rounds (so never both rejected and named).
    verdict : dict
        `verdict`: ``success`` (False whenever a residual is unexplained, the size scale's
        signature is contradicted or the stars' residual chi2 per pixel is far above its null
        expectation), ``reasons``, ``star_residual_chi2_per_pixel``, ``null_expectation``
        and ``limit``.
    empirical : dict or None
        When a size residual is left: the EMPIRICAL term learned from it
        (`bfpsf.model.empirical.EmpiricalTerm.to_dict`, label ``'empirical'``) with its
        out-of-sample ``validation`` (``heldout`` and, with 4 or more exposures,
        ``late_block``: slope residual and photometry bias before and after it, the late
        block's ``exposures`` and the ``term`` fitted on the early ones; ``validated``: it lowered the slope residual on every block, else `refine` leaves it
        out), with the patterns of `bfpsf.model.empirical.PATTERN_KIND`.
    empirical_alternatives : dict
        The same learned with each other pattern kind, by kind (``bfpsf diagnose`` keeps
        the one whose held-out star residual is the lower).
    folded : dict
        The joint fit of the selected effects a calibration can hold (``names``, ``effects``:
        name -> values, ``scale_nuisance``, ``split_nuisance``), for
        `bfpsf.diagnosis.refine`.
    ptc_curves : dict
        PTC residuals for the plot (empty without a PTC observable): ``mean_e``,
        ``residual_raw`` (data minus the calibrated sum-rule model, nothing refitted),
        ``residual_before``, ``residual_after`` (data minus base / final model with the
        nuisance refitted, e-^2), ``error``, ``var_e``.
    """

    residual_before: dict
    candidates: list
    selected: list
    residual_after: dict
    parameters: dict
    threshold: float
    curves: dict = field(default_factory=dict)
    ambiguous: dict = field(default_factory=dict)
    residual_physical: dict = None
    ptc_curves: dict = field(default_factory=dict)
    nuisance: dict = field(default_factory=dict)
    residual_before_heldout: dict = None
    residual_after_heldout: dict = None
    residual_physical_heldout: dict = None
    confirmed: dict = field(default_factory=dict)
    holdout: dict = None
    unexplained: list = field(default_factory=list)
    folded: dict = field(default_factory=dict)
    rejected: dict = field(default_factory=dict)
    verdict: dict = field(default_factory=dict)
    empirical: dict = None
    empirical_alternatives: dict = field(default_factory=dict)

    def to_json_dict(self):
        """The ``--json`` summary: residual_before, candidates, selected, residual_after (+)."""
        return json_safe({"residual_before": self.residual_before, "candidates": self.candidates,
                      "selected": self.selected, "residual_after": self.residual_after,
                      "parameters": self.parameters, "threshold": self.threshold,
                      "ambiguous": self.ambiguous,
                      "residual_physical": self.residual_physical, "nuisance": self.nuisance,
                      "residual_before_heldout": self.residual_before_heldout,
                      "residual_after_heldout": self.residual_after_heldout,
                      "residual_physical_heldout": self.residual_physical_heldout,
                      "confirmed": self.confirmed, "holdout": self.holdout,
                      "unexplained": self.unexplained, "folded": self.folded,
                      "rejected": self.rejected, "verdict": self.verdict,
                      "empirical": self.empirical,
                      "empirical_alternatives": self.empirical_alternatives})
