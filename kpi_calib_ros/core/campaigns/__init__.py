"""Campaigns over time: sequential measurement and change detection."""
