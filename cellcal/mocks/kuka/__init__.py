"""The KUKA twins: the controller with cellcal's KRL loop, and KUKAVARPROXY in front of it."""
