"""Multi-person tracking (thesis chapter 4): components, person classifier, filters, track life."""
