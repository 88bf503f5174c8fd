#include "eval/html_report.h"

#include <gtest/gtest.h>

#include <fstream>

#include "io/video.h"
#include "test_util.h"

namespace dojo::eval {
namespace {

using test::TempDir;

TEST(HtmlReport, Base64MatchesRfc4648Vectors) {
  EXPECT_EQ(base64_encode(""), "");
  EXPECT_EQ(base64_encode("f"), "Zg==");
  EXPECT_EQ(base64_encode("fo"), "Zm8=");
  EXPECT_EQ(base64_encode("foo"), "Zm9v");
  EXPECT_EQ(base64_encode("foob"), "Zm9vYg==");
  EXPECT_EQ(base64_encode("fooba"), "Zm9vYmE=");
  EXPECT_EQ(base64_encode("foobar"), "Zm9vYmFy");
  EXPECT_EQ(base64_encode(std::string("\xff\x00\x80", 3)), "/wCA");
}

TEST(HtmlReport, EscapesText) { EXPECT_EQ(html_escape("a<b & \"c\">"), "a&lt;b &amp; &quot;c&quot;&gt;"); }

TEST(HtmlReport, ReadsCsvColumnsAndSkipsEmptyCells) {
  TempDir dir;
  {
    std::ofstream f(dir / "loss.csv");
    f << "step,loss,probe\n1,0.5,\n2,0.25,0.3\n3,0.125,\n";
  }
  const auto loss = read_csv_series(dir / "loss.csv", "step", "loss", "l");
  EXPECT_EQ(loss.x, (std::vector<double>{1, 2, 3}));
  EXPECT_EQ(loss.y, (std::vector<double>{0.5, 0.25, 0.125}));
  const auto probe = read_csv_series(dir / "loss.csv", "step", "probe", "p");
  EXPECT_EQ(probe.x, (std::vector<double>{2}));
  EXPECT_EQ(probe.y, (std::vector<double>{0.3}));
  const auto missing = test::error_message([&] { read_csv_series(dir / "loss.csv", "step", "psnr", "x"); });
  EXPECT_NE(missing.find("loss.csv"), std::string::npos);
  EXPECT_NE(missing.find("psnr"), std::string::npos);
  EXPECT_NE(test::error_message([&] { read_csv_series(dir / "nope.csv", "a", "b", "x"); }).find("nope.csv"),
            std::string::npos);
}

TEST(HtmlReport, EmbedsVideosTablesAndCharts) {
  TempDir dir;
  const auto frames = torch::randint(0, 255, {4, 16, 16, 3}, torch::kByte);
  io::write_video((dir / "clip.mp4").string(), frames, {});
  HtmlReport report("Title <1>");
  report.table({"split", "PSNR"}, {{"val & test", "12.50"}});
  report.video(dir / "clip.mp4", "a clip");
  report.line_chart("loss", {{"run", {1, 2, 3, 4}, {4, 3, 2, 1}}}, "step", "loss", /*log_y=*/true,
                    /*smooth=*/2);
  report.write(dir / "report.html");
  const auto html = test::read_file(dir / "report.html");
  EXPECT_NE(html.find("<title>Title &lt;1&gt;</title>"), std::string::npos);
  EXPECT_NE(html.find("<td>val &amp; test</td><td>12.50</td>"), std::string::npos);
  // The whole mp4, byte for byte, as a data URI: the file opens without its neighbours.
  EXPECT_NE(html.find("data:video/mp4;base64," + base64_encode(test::read_file(dir / "clip.mp4"))),
            std::string::npos);
  // Four points, one polyline.
  const auto poly = html.find("<polyline");
  ASSERT_NE(poly, std::string::npos);
  const auto points = html.substr(html.find("points=\"", poly) + 8);
  EXPECT_EQ(std::count(points.begin(), points.begin() + points.find('"'), ','), 4);
  EXPECT_THROW(report.video(dir / "missing.mp4", "x"), std::exception);
}

}  // namespace
}  // namespace dojo::eval
