"""The replay package's error (under the project's root error, as an input error: exit code 2 in the CLI)."""

from __future__ import annotations

from normpos_grasp.errors import InputError


class BundleError(InputError):
    """A replay bundle is incomplete, corrupt (a file's SHA-256 differs from its manifest) or not a bundle at all."""
