"""Transport of the compensation table to the PLC (ADS via pyads, Modbus TCP via pymodbus)."""
