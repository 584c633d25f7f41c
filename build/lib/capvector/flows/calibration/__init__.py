"""A calibration before a study: its configuration, plan and flow."""
