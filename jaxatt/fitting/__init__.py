"""Gain tuning: constrained parametrizations (:mod:`jaxatt.fitting.parametrize`), the gains file
(:mod:`jaxatt.fitting.gainsfile`) and your params of any pytree shape as named gains
(:mod:`jaxatt.fitting.flatparams`), the one fitter (:mod:`jaxatt.fitting.fitter`), the variance-free loss
(:mod:`jaxatt.fitting.varfree`) and the filtering floor it is compared with (:mod:`jaxatt.fitting.floor`)."""
