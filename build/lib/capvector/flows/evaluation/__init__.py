"""Scoring checkpoints: the evaluate and reevaluate flows, schedules, protocols by name."""
