"""The hardware under test as the library models it: the motor's data sheet and the test bench's mechanics."""
