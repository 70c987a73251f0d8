"""Example cells and templates (installed as `normpos_grasp.examples`; copy them to start your own)."""
