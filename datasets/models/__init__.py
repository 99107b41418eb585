"""The built-in targets at model and true size (tanks, jets, ships, military trucks and the
civilian cars, vans, trucks and buses), their paint, and scanned targets. Imports nothing
else of :mod:`prism3d.datasets`."""
