"""Gain tuning: constrained parametrizations (:mod:`jaxatt.fitting.parametrize`), the gains file
(:mod:`jaxatt.fitting.gainsfile`) and the one fitter (:mod:`jaxatt.fitting.fitter`)."""
