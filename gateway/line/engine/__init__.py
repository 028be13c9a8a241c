"""The bus engine: what to read and when, its transactions, device health, the bus task."""
