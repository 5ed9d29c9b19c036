"""Structural analysis (report chapter 4): which faults the residuals can detect and isolate.

numpy/scipy only. Frisk's faultdiagnosistoolbox (optional extra ``structure``) is used in the tests
to cross-check the results, never at run time. The names below load on first use, so the live
nodes, which only read a residual set (``structure.model``), never load the analysis.
"""
from youbot_fdi.lazy import lazy_exports

_MODULE_OF = {'analyze': 'analysis', 'sensor_placement': 'analysis', 'StructuralAnalysis': 'analysis',
              'Equation': 'model', 'StructuralModel': 'model'}

__all__ = sorted(_MODULE_OF, key=str.lower)

__getattr__ = lazy_exports(__name__, _MODULE_OF)
