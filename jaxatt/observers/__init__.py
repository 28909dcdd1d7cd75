"""Observers, one module per paper/filter; each exposes Params, State, Out, make_observer, default_params."""
