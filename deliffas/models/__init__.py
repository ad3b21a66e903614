"""Networks, losses, metrics and the model zoo of DELIFFAS and its variants."""
