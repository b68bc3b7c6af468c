"""What leaves the product as files: the export writers and the QA report, shared by the API's
download routes and the `mmsclean export` command (which must not import a route module)."""
