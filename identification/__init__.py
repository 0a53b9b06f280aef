"""Excitation flights, flight-log datasets, symbolic regression, and the model file."""
