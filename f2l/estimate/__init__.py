"""The generic estimator: transport, Charbonnier loss, albedo and ground, multi-start L-BFGS."""

from f2l.estimate.estimator import (
    EstimateResult,
    EstimationError,
    EstimatorConfig,
    FaceObservation,
    estimate,
)

__all__ = ["EstimateResult", "EstimationError", "EstimatorConfig", "FaceObservation", "estimate"]
