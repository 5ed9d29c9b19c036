"""Structural analysis (report chapter 4): which faults the residuals can detect and isolate.

numpy/scipy only. Frisk's faultdiagnosistoolbox (optional extra ``structure``) is used in the tests
to cross-check the results, never at run time.
"""
from youbot_fdi.structure.analysis import analyze, sensor_placement, StructuralAnalysis
from youbot_fdi.structure.model import Equation, StructuralModel

__all__ = ['analyze', 'Equation', 'sensor_placement', 'StructuralAnalysis', 'StructuralModel']
