"""Model-mismatch diagnosis: locate where simulation and recording disagree, name the
physics left out from a catalogue of extensions, fit it, and show held-out prediction improve.

Modules: `covariates` (signals from the poses), `locate` (profiles and honest statistics),
`catalogue` (extensions as sim.Modifiers), `fit` (passes, cross-validated coefficients),
`run` (the diagnosis and its verdict), `report` (diagnosis.json, report.md, figures).
"""

from torchsoil.diagnosis.phases import Diagnosis, DiagnosisConfig, diagnose

__all__ = ["Diagnosis", "DiagnosisConfig", "diagnose"]
