"""Diagnosis: where a model and recordings differ, which physics is missing, and the model with it added.

``diagnose(model, recordings, factors=...)`` returns a :class:`Diagnosis`; :func:`write_report` writes
the Markdown and JSON report, the figures and the extended model file. See ``gateway/diagnose/api.py``
for the steps and ``cncgw diagnose --help`` for the command.
"""

from gateway.diagnose.api import Diagnosis, diagnose, factor_infos
from gateway.diagnose.data import DiagnosisError
from gateway.diagnose.hypotheses import FactorInfo
from gateway.diagnose.output import write_report
from gateway.diagnose.search import Options

__all__ = ["Diagnosis", "DiagnosisError", "FactorInfo", "Options", "diagnose", "factor_infos",
           "write_report"]
