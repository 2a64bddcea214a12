"""World models: DeLaN, the DeLaN ensemble, the Gaussian MLP ensemble, inverse-dynamics models.

Submodules are imported on demand (``from mbrl_delan.models.delan import DeLaN``).
"""
