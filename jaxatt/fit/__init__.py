"""Gain tuning: constrained parametrizations (:mod:`jaxatt.fit.parametrize`), the gains file
(:mod:`jaxatt.fit.gainsfile`) and the one fitter (:mod:`jaxatt.fit.fitter`)."""
