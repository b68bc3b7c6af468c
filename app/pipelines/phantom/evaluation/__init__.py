"""Scoring phantom runs against reference labels: the reference pillar classes (`reference`, also
the training labels), the paper's Table I / II metrics of a run's pillar and point classes
(`classification_metrics`) and the two density baselines of Table II (`baselines`)."""
