"""How runs are assembled from their configs (the fit's inverse-dynamics models: `inverse`)."""
