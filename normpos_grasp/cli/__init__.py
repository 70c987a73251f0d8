"""Command-line interface: `normpos-grasp <command>`; one module per command, registered in `main.py`."""
