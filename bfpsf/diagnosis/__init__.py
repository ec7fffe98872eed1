"""The closed loop: residual -> missing effect -> added -> before / after (on held-out data).

One module per job:

- `bfpsf.diagnosis.observables`: the observable tables and their builders (images, sizes);
- `bfpsf.diagnosis.spot_model`: the base model of the spot sizes (the model layer's
  redistribution of a model spot);
- `bfpsf.diagnosis.catalogue`: the candidate effects and their templates;
- `bfpsf.diagnosis.loop`: the information-criterion loop, the held-out split and the
  description of what no candidate explains;
- `bfpsf.diagnosis.readers`: the published measured tables;
- `bfpsf.diagnosis.star_residual`: the stacked residual of the stars against P(F);
- `bfpsf.diagnosis.refine`: the loop's result written as a calibration;
- `bfpsf.diagnosis.signature`: attribution by signature (a candidate is named only when its
  template matches in every observable, axis, position and exposure block and in parity);
- `bfpsf.diagnosis.odd_moments`: the stars' skewness (the odd part of the residual);
- `bfpsf.diagnosis.empirical_fit`: the EMPIRICAL term learned from what is left, validated
  out of sample (its model: `bfpsf.model.empirical`);
- `bfpsf.diagnosis.pattern_choice`: the held-out stars' pixels against a refined
  calibration, and the EMPIRICAL pattern kind they prefer;
- `bfpsf.diagnosis.quiet_axis`: the flats' BF scale fitted on the axis an undeclared effect
  leaves alone;
- `bfpsf.validation.effects_bench`: a bench of effects outside the catalogue (and the null and
  catalogue effects) applied to the same simulated spots.
"""
