"""One module per stage: plain functions that turn input items into output items. No Ray here."""
