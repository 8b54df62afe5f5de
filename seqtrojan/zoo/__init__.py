"""Model zoos of clean and backdoored agents, built locally or on Ray."""
