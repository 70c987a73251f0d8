"""CAD templates (known structure) and pose fitting of templates to measured norm-positions."""

from normpos_grasp.templates.model import GraspAnnotation, Symmetry, Template, TemplateFit

__all__ = ["GraspAnnotation", "Symmetry", "Template", "TemplateFit"]
