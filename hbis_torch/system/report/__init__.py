"""The pictures and the HTML report of a run of the whole system."""
