"""The traffic simulation: SUMO through libsumo."""
