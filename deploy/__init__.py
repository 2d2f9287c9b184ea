"""The site files and deploy scripts, shipped with the package (``telesurg.deploy``)."""
