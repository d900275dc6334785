"""The auction against morph-sim's conformance kit, in the lab and in a distributed run."""

from morph_sim.testing import check_policy


def test_the_auction_conforms():
    check_policy("morph_auction.policy:AuctionPolicy")


def test_the_auction_conforms_with_one_bid_and_no_memory():
    check_policy("morph_auction.policy:AuctionPolicy", {"max_bids": 1, "max_age": 0}, distributed=False)
