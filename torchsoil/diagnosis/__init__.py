"""Model-mismatch diagnosis: locate where simulation and recording disagree, name the
physics left out from a catalogue of extensions, fit it, and show held-out prediction improve.

Modules: `covariates` (signals from the poses), `stats` (honest statistics of arrays: paired
tests, effective sample sizes, folds, levels), `locate` (profiles and spectral lines),
`catalogue` (extensions as sim.Modifiers), `fit` (passes, cross-validated coefficients),
`phases` (the diagnosis, phase by phase, and its verdict), `parallel` (its independent passes
on an engine), `checkpoint` (finished passes kept on disk), `report` (diagnosis.json,
report.md, figures).
"""

from torchsoil.diagnosis.phases import Diagnosis, DiagnosisConfig, diagnose

__all__ = ["Diagnosis", "DiagnosisConfig", "diagnose"]
