"""CAD templates (known structure) and pose fitting of templates to measured norm-positions."""

from normpos_grasp.records.template import GraspAnnotation, Symmetry, Template, TemplateFit

__all__ = [
    "FitContext",
    "FitOptions",
    "GraspAnnotation",
    "Symmetry",
    "Template",
    "TemplateFit",
    "TemplateLibrary",
    "fit_best",
    "fit_best_or_raise",
    "fit_many",
    "fit_template",
    "fit_template_or_raise",
    "load_library",
    "load_template",
    "save_template",
]


def __getattr__(name: str) -> object:
    """Lazy access to the fitting and library API (keeps `import normpos_grasp.templates` light)."""
    if name in (
        "FitContext",
        "FitOptions",
        "fit_best",
        "fit_best_or_raise",
        "fit_many",
        "fit_template",
        "fit_template_or_raise",
    ):
        from normpos_grasp.templates import fit

        return getattr(fit, name)
    if name in ("TemplateLibrary", "load_library", "load_template", "save_template"):
        from normpos_grasp.templates import library

        return getattr(library, name)
    raise AttributeError(f"module 'normpos_grasp.templates' has no attribute '{name}'")
