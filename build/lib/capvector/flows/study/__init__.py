"""A study: its configuration, plan, flow and report."""
