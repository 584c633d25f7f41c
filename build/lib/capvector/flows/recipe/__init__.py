"""The recipe run once: its configuration, plan, flow, sweep and report."""
