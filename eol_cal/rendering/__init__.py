"""What reaches a person: display units, matplotlib (text taken literally) and PNG files."""
