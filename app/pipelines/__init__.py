"""Pipelines: clutter, phantom and guardrail, one folder each, steps named after the papers."""
