"""Scoring guardrail runs against reference labels (`reference`: what counts as a guardrail, per
point and per slice) and reconstructions against the simulator's exact models
(`reconstruction_metrics`)."""
