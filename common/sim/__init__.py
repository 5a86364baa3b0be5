"""What stands in for absent hardware and people: the simulated UR16e and the operator twin."""
