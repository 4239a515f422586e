"""What a clinic reads from a scan: limb measurements at landmark levels, comparisons
between sides and visits, and the clinical report (PDF, CSV)."""
