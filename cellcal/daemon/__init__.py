"""The campaign: plan, engine, store, analysis, and the service around them."""
