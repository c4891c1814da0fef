"""deformnet: the learning half of mousetrack.

Body model, deformable-mouse simulator (`deformnet.sim`), tokens, sequence nets (LSTM,
transformer), their Lightning modules, and `DeformationModel`. Never imports `adjust`.
"""

__all__ = ["__version__"]
__version__ = "0.1.0"
