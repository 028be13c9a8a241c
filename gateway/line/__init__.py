"""The line: the bus owner (port, read plan, schedule, transactions, device health) and scan."""
