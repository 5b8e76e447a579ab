"""The test suite (a package, so its subpackages can never shadow the product's: ``import drivers`` in a test is always the product)."""
