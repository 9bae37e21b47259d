"""Drape client SDK: submit cloths to a Drape server over Zenoh and receive their state."""
