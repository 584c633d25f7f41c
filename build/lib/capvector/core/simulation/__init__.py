"""Meta-World: task names, environments, observation maps, depth targets, expert demos."""
